"""Gymnasium vector env over :class:`~uwb_env.batch.BatchedSystem`: many scheduler envs in numpy.

``CalibrationSchedulingVectorEnv(num_envs=32, config=None, **overrides)`` behaves like
``gymnasium.make_vec("uwb_env/CalibrationScheduling-v0", num_envs)`` (same observation,
action, reward), but steps all copies together; it is the registration's ``vector_entry_point``
(``gymnasium.make_vec(..., vectorization_mode="vector_entry_point")``).

Autoreset (``autoreset_mode``, Gymnasium 1.x conventions; all copies truncate together after
``max_cycles``):

- ``AutoresetMode.NEXT_STEP`` (default; what Gymnasium's vector wrappers such as
  ``RecordEpisodeStatistics`` and the observation wrappers expect): the truncating step returns
  the last observations; the next ``step`` ignores its actions, resets every copy and returns
  the reset observations with zero reward.
- ``AutoresetMode.SAME_STEP``: the truncating step returns the reset observations, with the last
  ones in ``infos["final_obs"]`` and their infos in ``infos["final_info"]``.

``reset(seed=s)`` seeds the batch's one generator; ``reset(seed=[s0, s1, ...])`` (one per copy,
Gymnasium's convention) seeds it from the whole list (a copy is not the single env of its seed:
the copies share one generator). Infos are dicts of arrays (``mean_tag_error_m``,
``mean_anchor_error_m``, ``calibrating_fraction``, ``round_started``, ``calibration_count``).
2D only (see :mod:`uwb_env.batch`).
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
    metadata = {"autoreset_mode": AutoresetMode.NEXT_STEP, "render_modes": []}

    def __init__(self, num_envs: int = 16, config=None, autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP,
                 **overrides: Any):
        mode = AutoresetMode(autoreset_mode)
        if mode not in (AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP):
            raise ValueError(f"autoreset_mode={autoreset_mode!r}: NEXT_STEP or SAME_STEP")
        self.metadata = {**type(self).metadata, "autoreset_mode": mode}
        self.autoreset_mode = mode
        self._needs_reset = False
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

    def reset(self, *, seed: int | list[int] | None = None, options: dict | None = None):
        if seed is not None:
            if isinstance(seed, (list, tuple, np.ndarray)):
                if len(seed) != self.num_envs or any(s is None for s in seed):
                    raise ValueError(f"seed: expected {self.num_envs} integers (one per copy), got {seed!r}")
                self.np_random = np.random.Generator(np.random.PCG64(np.random.SeedSequence([int(s) for s in seed])))
            else:
                self.np_random, _ = seeding.np_random(seed)
        self.system.reset(self.np_random)
        self.num_steps = 0
        self._needs_reset = False
        return self._obs(), {}

    def step(self, actions):
        actions = np.asarray(actions)
        if actions.shape != (self.num_envs,) or not np.isin(actions, (0, 1)).all():
            raise ValueError(f"actions={actions!r}: expected {self.num_envs} values in {{0, 1}}")
        if self._needs_reset:  # NEXT_STEP: this step only resets (its actions are ignored)
            obs, _ = self.reset()
            zeros = np.zeros(self.num_envs, dtype=bool)
            return obs, np.zeros(self.num_envs), zeros, zeros.copy(), {}
        report = self.system.step(actions == 1)
        reward, tag, anchor = self.system.rewards(report)
        self.num_steps += 1
        truncated = np.full(self.num_envs, self.num_steps >= self.config.max_cycles)
        infos = {"mean_tag_error_m": tag, "mean_anchor_error_m": anchor,
                 "calibrating_fraction": report["calibrating_fraction"], "round_started": report["round_started"],
                 "calibration_count": self.system.calibration_count.copy()}
        obs = self._obs()
        if truncated[0] and self.autoreset_mode == AutoresetMode.SAME_STEP:
            infos = {**infos, "final_obs": obs, "final_info": dict(infos),
                     "_final_obs": truncated.copy(), "_final_info": truncated.copy()}
            obs, _ = self.reset()
        elif truncated[0]:
            self._needs_reset = True
        return obs, reward.astype(np.float64), np.zeros(self.num_envs, dtype=bool), truncated, infos

    def _obs(self) -> np.ndarray:
        return self.system.features().reshape(self.num_envs, -1)
