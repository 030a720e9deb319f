"""Gymnasium vector env over :class:`~uwb_env.batch.BatchedSystem`: many scheduler envs in numpy.

``CalibrationSchedulingVectorEnv(num_envs=32, config=None, **overrides)`` behaves like
``gymnasium.make_vec("uwb_env/CalibrationScheduling-v0", num_envs)`` (same observation,
action, reward), but steps all copies together. Autoreset mode ``SAME_STEP``: all copies
truncate together after ``max_cycles``; that step returns the reset observations, with the
last ones in ``infos["final_obs"]`` and their infos in ``infos["final_info"]``. Infos are dicts
of arrays (``mean_tag_error_m``, ``mean_anchor_error_m``, ``calibrating_fraction``,
``round_started``, ``calibration_count``). 2D only (see :mod:`uwb_env.batch`).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium import spaces
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from uwb_env.batch import BatchedSystem
from uwb_env.env.parallel_env import make_config


class CalibrationSchedulingVectorEnv(VectorEnv):
    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP, "render_modes": []}

    def __init__(self, num_envs: int = 16, config=None, **overrides: Any):
        self.config = make_config(config, overrides)
        self.system = BatchedSystem(self.config, num_envs)
        self.num_envs = num_envs
        n = self.config.sim.n_anchors
        low, high = self.system.obs_low, self.system.obs_high
        self.single_observation_space = spaces.Box(np.tile(low, n), np.tile(high, n), dtype=np.float32)
        self.single_action_space = spaces.Discrete(2)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self.np_random, _ = seeding.np_random(None)
        self.num_steps = 0

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        if seed is not None:
            self.np_random, _ = seeding.np_random(seed)
        self.system.reset(self.np_random)
        self.num_steps = 0
        return self._obs(), {}

    def step(self, actions):
        actions = np.asarray(actions)
        if actions.shape != (self.num_envs,) or not np.isin(actions, (0, 1)).all():
            raise ValueError(f"actions={actions!r}: expected {self.num_envs} values in {{0, 1}}")
        report = self.system.step(actions == 1)
        reward, tag, anchor = self.system.rewards(report)
        self.num_steps += 1
        truncated = np.full(self.num_envs, self.num_steps >= self.config.max_cycles)
        infos = {"mean_tag_error_m": tag, "mean_anchor_error_m": anchor,
                 "calibrating_fraction": report["calibrating_fraction"], "round_started": report["round_started"],
                 "calibration_count": self.system.calibration_count.copy()}
        obs = self._obs()
        if truncated[0]:
            infos = {**infos, "final_obs": obs, "final_info": dict(infos),
                     "_final_obs": truncated.copy(), "_final_info": truncated.copy()}
            obs, _ = self.reset()
        return obs, reward.astype(np.float64), np.zeros(self.num_envs, dtype=bool), truncated, infos

    def _obs(self) -> np.ndarray:
        return self.system.features().reshape(self.num_envs, -1)
