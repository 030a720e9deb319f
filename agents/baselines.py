"""Baseline calibration schedulers (all implement the policy hook).

Every policy requests a calibration from *all* anchors at once (so any trigger rule fires),
and decides from the observations alone unless ``uses_ground_truth`` is True.
"""

from __future__ import annotations

import numpy as np

from uwb_env.system import OBS_FIELDS

# Column of a field in an anchor's observation vector, counted from the end (dim-independent).
_FROM_END = {name: i - len(OBS_FIELDS) for i, name in enumerate(OBS_FIELDS)}


def _field(observations: dict[str, np.ndarray], name: str) -> np.ndarray:
    return np.array([obs[_FROM_END[name]] for obs in observations.values()])


def _all(observations: dict[str, np.ndarray], request: bool) -> dict[str, int]:
    return {agent: int(request) for agent in observations}


def _positive(name: str, value: float) -> float:
    if not value > 0:
        raise ValueError(f"{name}={value!r}: must be > 0")
    return value


class _Stateless:
    """Shared defaults: observation-only and nothing to reset."""

    uses_ground_truth = False

    def reset(self, seed: int | None = None) -> None:
        pass


class FixedIntervalPolicy:
    """The paper's baseline: request a calibration every ``interval_steps`` steps (or every
    ``interval_s`` seconds at ``dt_s``); rounds start exactly every k steps while k is longer
    than a round (requests during a round are ignored by the env)."""

    uses_ground_truth = False

    def __init__(self, interval_steps: int | None = 10, interval_s: float | None = None, dt_s: float = 0.2):
        if (interval_steps is None) == (interval_s is None):
            raise ValueError("give exactly one of interval_steps or interval_s")
        steps = interval_steps if interval_steps is not None else int(round(interval_s / dt_s))
        if steps < 1:
            raise ValueError(f"interval_steps={steps!r}: must be >= 1")
        self.interval_steps = steps
        self.t = 0

    def reset(self, seed: int | None = None) -> None:
        self.t = 0

    def act(self, observations, infos):
        self.t += 1
        return _all(observations, self.t % self.interval_steps == 0)


class UncertaintyThresholdPolicy(_Stateless):
    """Calibrate when any anchor's predicted position std exceeds ``threshold_m`` (the
    paper's "whenever the inter-calibration positioning error at the anchors exceeds a
    certain error threshold", with the error predicted from the drift model)."""

    def __init__(self, threshold_m: float = 0.15):
        self.threshold_m = _positive("threshold_m", threshold_m)

    def act(self, observations, infos):
        return _all(observations, bool((_field(observations, "predicted_position_std_m") > self.threshold_m).any()))


class ResidualTriggerPolicy(_Stateless):
    """Calibrate when the tag fixes' residuals show stale anchors: the windowed mean RMS
    tag-fix residual exceeds ``threshold_m``."""

    def __init__(self, threshold_m: float = 0.12):
        self.threshold_m = _positive("threshold_m", threshold_m)

    def act(self, observations, infos):
        residual = _field(observations, "tag_fix_rms_residual_m").max()
        return _all(observations, bool(residual > self.threshold_m))


class NeverPolicy(_Stateless):
    def act(self, observations, infos):
        return _all(observations, False)


class AlwaysPolicy(_Stateless):
    def act(self, observations, infos):
        return _all(observations, True)


class RandomPolicy:
    """Request with probability ``rate`` per step (its own generator, seeded by ``reset``)."""

    uses_ground_truth = False

    def __init__(self, rate: float = 0.05):
        if not 0 <= rate <= 1:
            raise ValueError(f"rate={rate!r}: must be in [0, 1]")
        self.rate = rate
        self.rng = np.random.default_rng()

    def reset(self, seed: int | None = None) -> None:
        self.rng = np.random.default_rng(seed)

    def act(self, observations, infos):
        return _all(observations, bool(self.rng.random() < self.rate))


class OraclePolicy(_Stateless):
    """GROUND TRUTH (a bound, not deployable): calibrate when the true mean anchor error,
    read from ``infos["mean_anchor_error_m"]``, exceeds ``threshold_m``."""

    uses_ground_truth = True

    def __init__(self, threshold_m: float = 0.1):
        self.threshold_m = _positive("threshold_m", threshold_m)

    def act(self, observations, infos):
        if not infos:
            return _all(observations, False)
        error = next(iter(infos.values()))["mean_anchor_error_m"]
        return _all(observations, error > self.threshold_m)
