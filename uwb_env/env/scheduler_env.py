"""Gymnasium env for a centralized calibration scheduler (one decision for the whole team).

## Description
The same task as :class:`~uwb_env.env.parallel_env.UWBCalibrationParallelEnv`, seen by one
central scheduler: every step it decides whether the team starts a calibration round.

## Action space
``Discrete(2)``: 0 = do not calibrate, 1 = start a calibration round (ignored, and counted,
while a round runs).

## Observation space
``Box((n_anchors * (dim + 8),), float32)``: the anchors' feature vectors (see the parallel
env's table) concatenated in anchor order.

## Rewards, starting state, episode end
As in the parallel env (team reward; truncation after ``max_cycles``; never terminated).

## Arguments
``gymnasium.make("uwb_env/CalibrationScheduling-v0", config=None, render_mode=None, **overrides)``;
``backend=`` a :class:`~uwb_env.hardware.backend.HardwareWorld` runs it on DWM1001 devices (as the
parallel env: no ground truth, residual-proxy reward).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from uwb_env.config import EnvConfig
from uwb_env.env.parallel_env import _PLAIN_INTS, UWBCalibrationParallelEnv


class CalibrationSchedulingEnv(gym.Env):
    """See the module docstring."""

    metadata = {"render_modes": ["human", "rgb_array"], "render_fps": 10}

    def __init__(self, config: EnvConfig | dict | None = None, render_mode: str | None = None, backend=None,
                 **overrides: Any):
        self.parallel = UWBCalibrationParallelEnv(config, render_mode=render_mode, backend=backend, **overrides)
        if self.parallel.config.action_mode != "calibrate":
            raise ValueError("action_mode: the scheduler env supports only 'calibrate'")
        self.config = self.parallel.config
        self.render_mode = render_mode
        agents = self.parallel.possible_agents
        per = self.parallel.observation_space(agents[0])
        self.observation_space = spaces.Box(np.tile(per.low, len(agents)), np.tile(per.high, len(agents)),
                                            dtype=np.float32)
        self.action_space = spaces.Discrete(2)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        # One generator for the whole env: the parallel env draws from ours.
        self.parallel.np_random = self.np_random
        obs, infos = self.parallel.reset(options=options)
        return self._flat(obs), self._info(infos)

    def step(self, action):
        # plain ints (the usual case) checked without Space.contains' conversions
        if not (type(action) in _PLAIN_INTS and 0 <= action < self.action_space.n) \
                and not self.action_space.contains(action):
            raise ValueError(f"action={action!r}: not in {self.action_space}")
        actions = {a: int(action) for a in self.parallel.agents}
        obs, rewards, _, truncs, infos = self.parallel.step(actions)
        agent = self.parallel.possible_agents[0]
        return self._flat(obs), rewards[agent], False, bool(truncs[agent]), self._info(infos)

    def render(self):
        return self.parallel.render()

    def close(self) -> None:
        self.parallel.close()

    def _flat(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        if not obs:  # after truncation the parallel env has no agents left: observe the state
            return self.parallel.system.anchor_features().ravel()
        return np.concatenate([obs[a] for a in self.parallel.possible_agents])

    def _info(self, infos: dict[str, dict]) -> dict:
        if not infos:
            return {}
        first = next(iter(infos.values()))
        return {k: v for k, v in first.items() if k != "anchor_error_m"} | {
            "anchor_errors_m": np.array([infos[a]["anchor_error_m"] for a in infos])
        }
