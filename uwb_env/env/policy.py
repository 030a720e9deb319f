"""The policy hook: how any scheduler (heuristic, trained model, user code) plugs in.

A policy implements :class:`CalibrationPolicy`: ``reset(seed)`` at the start of an episode and
``act(observations, infos) -> actions`` every step, with PettingZoo's per-agent dicts.
:func:`rollout` runs one episode and returns per-step metrics.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np


@runtime_checkable
class CalibrationPolicy(Protocol):
    """Decides, every step, which anchors request a calibration.

    ``uses_ground_truth`` must be True for policies that read ground-truth keys of ``infos``
    (e.g. the oracle): such a policy is a bound, not something deployable.
    """

    uses_ground_truth: bool

    def reset(self, seed: int | None = None) -> None: ...

    def act(self, observations: dict[str, np.ndarray], infos: dict[str, dict]) -> dict[str, int]: ...


@dataclass
class RolloutResult:
    """Per-step metrics of one episode (arrays of length = steps)."""

    tag_error_m: np.ndarray
    anchor_error_m: np.ndarray
    calibrating: np.ndarray  # fraction of each step the channel was busy calibrating
    reward: np.ndarray
    round_started: np.ndarray
    calibration_count: int
    dt_s: float
    extras: dict[str, Any] = field(default_factory=dict)

    @property
    def steps(self) -> int:
        return len(self.reward)

    def summary(self) -> dict[str, float]:
        minutes = self.steps * self.dt_s / 60.0
        return {
            "mean_tag_error_m": float(self.tag_error_m.mean()),
            "median_tag_error_m": float(np.median(self.tag_error_m)),
            "p95_tag_error_m": float(np.percentile(self.tag_error_m, 95)),
            "mean_anchor_error_m": float(self.anchor_error_m.mean()),
            "calibrations_per_min": float(self.round_started.sum() / minutes) if minutes else 0.0,
            "fraction_calibrating": float(self.calibrating.mean()),
            "return": float(self.reward.sum()),
        }


def rollout(env, policy: CalibrationPolicy, seed: int | None = None, max_steps: int | None = None) -> RolloutResult:
    """Run one episode of a ParallelEnv under ``policy``; returns per-step metrics."""
    policy.reset(seed)
    obs, infos = env.reset(seed=seed)
    rows = []
    started = []
    steps = 0
    while env.agents and (max_steps is None or steps < max_steps):
        actions = policy.act(obs, infos)
        obs, rewards, _, _, infos = env.step(actions)
        info = next(iter(infos.values()))
        rows.append((info["mean_tag_error_m"], info["mean_anchor_error_m"], info["calibrating_fraction"],
                     next(iter(rewards.values()))))
        started.append(info["round_started"])
        steps += 1
    data = np.array(rows, dtype=float).reshape(-1, 4)
    return RolloutResult(
        tag_error_m=data[:, 0], anchor_error_m=data[:, 1], calibrating=data[:, 2], reward=data[:, 3],
        round_started=np.array(started, dtype=bool), calibration_count=int(info["calibration_count"]) if rows else 0,
        dt_s=env.config.sim.dt_s,
    )
