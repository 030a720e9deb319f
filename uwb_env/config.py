"""Frozen, validated configuration dataclasses for every part of the simulator.

Every field carries its unit in its name. Construction validates each value and raises
:class:`ConfigError` naming the field and the offending value; ``from_dict`` rejects unknown
keys (a misspelt key is a bug, not a default). Nested dicts merge into nested configs.

Example::

    cfg = SimConfig.from_dict({"n_anchors": 6, "ranging": {"nlos_probability": 0.1}})
    cfg = cfg.replace(dt_s=0.5)
"""

from __future__ import annotations

import dataclasses
import math
import typing
from dataclasses import dataclass, field
from typing import Any, TypeVar

C = TypeVar("C", bound="ConfigBase")


class ConfigError(ValueError):
    """A configuration value is invalid or a key is unknown.

    Attributes:
        field: dotted path of the offending field (``"ranging.nlos_probability"``).
        value: the rejected value.
    """

    def __init__(self, field_name: str, value: Any, reason: str):
        self.field = field_name
        self.value = value
        super().__init__(f"{field_name}={value!r}: {reason}")


class UnknownConfigKeyError(ConfigError, TypeError):
    """An unknown configuration key. Also a ``TypeError``: an env constructor given a keyword it
    does not take (TorchRL's ``GymEnv`` passes ``frameskip=1`` and tolerates only TypeError)
    behaves like any Python callable."""

    def __init__(self, field_name: str, value: Any = None, reason: str | None = None):
        if reason is None:  # re-raised by a client with one message (gymnasium.make does)
            Exception.__init__(self, field_name)
            self.field, self.value = None, None
        else:
            super().__init__(field_name, value, reason)


@dataclass(frozen=True)
class ConfigBase:
    """Shared strict construction, merging and validation helpers."""

    @classmethod
    def from_dict(cls: type[C], data: dict[str, Any] | None = None, *, _prefix: str = "") -> C:
        """Build from a (possibly partial, possibly nested) dict; unknown keys raise."""
        data = dict(data or {})
        hints = typing.get_type_hints(cls)
        known = {f.name: f for f in dataclasses.fields(cls)}
        kwargs: dict[str, Any] = {}
        for key, value in data.items():
            if key not in known:
                raise UnknownConfigKeyError(
                    _prefix + key, value, f"unknown key for {cls.__name__}; known: {sorted(known)}"
                )
            sub = hints[key]
            if isinstance(sub, type) and issubclass(sub, ConfigBase):
                if isinstance(value, sub):
                    kwargs[key] = value
                elif isinstance(value, dict):
                    kwargs[key] = sub.from_dict(value, _prefix=f"{_prefix}{key}.")
                else:
                    raise ConfigError(_prefix + key, value, f"expected a dict or {sub.__name__}")
            elif isinstance(value, list):
                kwargs[key] = tuple(tuple(v) if isinstance(v, list) else v for v in value)
            else:
                kwargs[key] = value
        try:
            return cls(**kwargs)
        except ConfigError as err:
            if _prefix and not err.field.startswith(_prefix):
                raise ConfigError(_prefix + err.field, err.value, str(err).split(": ", 1)[1]) from None
            raise

    def replace(self: C, **changes: Any) -> C:
        """Return a copy with ``changes`` applied; nested dicts merge into nested configs."""
        merged = self.to_dict()
        _deep_merge(merged, changes)
        return type(self).from_dict(merged)

    def to_dict(self) -> dict[str, Any]:
        """Plain nested dict (JSON/YAML friendly)."""
        out: dict[str, Any] = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            out[f.name] = value.to_dict() if isinstance(value, ConfigBase) else value
        return out

    # -- validation helpers (called from __post_init__) --------------------------------
    def _finite(self, name: str) -> float:
        value = getattr(self, name)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise ConfigError(name, value, "must be a finite number")
        return float(value)

    def _positive(self, *names: str) -> None:
        for name in names:
            if self._finite(name) <= 0:
                raise ConfigError(name, getattr(self, name), "must be > 0")

    def _non_negative(self, *names: str) -> None:
        for name in names:
            if self._finite(name) < 0:
                raise ConfigError(name, getattr(self, name), "must be >= 0")

    def _probability(self, *names: str) -> None:
        for name in names:
            if not 0.0 <= self._finite(name) <= 1.0:
                raise ConfigError(name, getattr(self, name), "must be a probability in [0, 1]")

    def _integer(self, name: str, lo: int, hi: int | None = None) -> None:
        value = getattr(self, name)
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(name, value, "must be an integer")
        if value < lo or (hi is not None and value > hi):
            raise ConfigError(name, value, f"must be in [{lo}, {hi if hi is not None else 'inf'}]")

    def _choice(self, name: str, choices: tuple[str, ...]) -> None:
        value = getattr(self, name)
        if value not in choices:
            raise ConfigError(name, value, f"must be one of {choices}")

    def _ordered(self, lo_name: str, hi_name: str) -> None:
        if getattr(self, lo_name) > getattr(self, hi_name):
            raise ConfigError(
                hi_name, getattr(self, hi_name), f"must be >= {lo_name}={getattr(self, lo_name)!r}"
            )


def _deep_merge(base: dict[str, Any], changes: dict[str, Any]) -> None:
    for key, value in changes.items():
        if isinstance(value, dict) and isinstance(base.get(key), dict):
            _deep_merge(base[key], value)
        elif isinstance(value, ConfigBase):
            base[key] = value.to_dict()
        else:
            base[key] = value


MOTION_MODELS = ("heading", "random_waypoint", "stop_and_go", "static", "patrol", "inside_hull")


@dataclass(frozen=True)
class MotionConfig(ConfigBase):
    """How robots (anchors or tags) move.

    ``heading`` is the paper's model: each robot keeps a heading and every move gets Gaussian
    noise. ``random_waypoint`` drives to uniformly drawn waypoints and pauses there.
    ``stop_and_go`` is ``heading`` with random pauses. Robots reflect off the area's walls.
    ``patrol`` (the default for anchors): random waypoints within ``patrol_radius_m`` of the
    robot's starting slot, so the team keeps the formation it was deployed in around the work
    area. ``inside_hull`` (the default for tags): random waypoints inside the polygon of the
    anchors' starting slots, so tags stay where the anchors can localize them (the paper's
    setup: tags inside the anchors' polygon). Speeds and pause lengths are drawn per robot per
    episode, so scenarios differ.
    """

    model: str = "heading"
    speed_min_mps: float = 0.2
    speed_max_mps: float = 0.6
    heading_noise_std_rad_per_sqrt_s: float = 0.15
    position_noise_std_m_per_sqrt_s: float = 0.01
    pause_rate_per_s: float = 0.05
    pause_min_s: float = 1.0
    pause_max_s: float = 6.0
    patrol_radius_m: float = 1.5

    def __post_init__(self) -> None:
        self._choice("model", MOTION_MODELS)
        self._positive("patrol_radius_m")
        self._non_negative(
            "speed_min_mps",
            "heading_noise_std_rad_per_sqrt_s",
            "position_noise_std_m_per_sqrt_s",
            "pause_rate_per_s",
            "pause_min_s",
        )
        self._finite("speed_max_mps")
        self._finite("pause_max_s")
        self._ordered("speed_min_mps", "speed_max_mps")
        self._ordered("pause_min_s", "pause_max_s")


ODOMETRY_MODELS = ("uniform", "distance")


@dataclass(frozen=True)
class OdometryConfig(ConfigBase):
    """How each anchor's on-board position estimate drifts between calibrations.

    ``uniform`` is the paper's: every step each axis of the estimate gets U(-e, +e) with
    e = ``uniform_error_m`` (variance e^2/3 per axis per step). ``distance`` integrates
    displacements with a per-robot scale error, a heading (yaw) error that random-walks with
    distance and turning, and white noise growing with the square root of the distance; robots
    enter "slip" phases (rate ``slip_rate_per_s``) in which the noise is multiplied, so drift
    varies over time and between robots.
    """

    model: str = "distance"
    uniform_error_m: float = 0.1
    noise_std_m_per_sqrt_m: float = 0.03
    scale_error_std: float = 0.02
    yaw_noise_std_rad_per_sqrt_m: float = 0.01
    yaw_noise_std_rad_per_rad: float = 0.02
    slip_rate_per_s: float = 0.02
    slip_duration_s: float = 8.0
    slip_noise_multiplier: float = 6.0

    def __post_init__(self) -> None:
        self._choice("model", ODOMETRY_MODELS)
        self._non_negative(
            "uniform_error_m",
            "noise_std_m_per_sqrt_m",
            "scale_error_std",
            "yaw_noise_std_rad_per_sqrt_m",
            "yaw_noise_std_rad_per_rad",
            "slip_rate_per_s",
        )
        self._positive("slip_duration_s")
        if self._finite("slip_noise_multiplier") < 1.0:
            raise ConfigError("slip_noise_multiplier", self.slip_noise_multiplier, "must be >= 1")


@dataclass(frozen=True)
class RangingConfig(ConfigBase):
    """UWB two-way ranging: measured = slope * d + offset + noise (+ NLOS bias).

    Slope, offset and noise std are fitted at load time from the measured DWM1001 data shipped
    in the package (``uwb_env/data/dwm1001_los_ranges.csv``); set ``noise_std_m`` to override
    the fitted std. NLOS adds an exponential positive bias with probability
    ``nlos_probability``; a range is lost with ``dropout_probability`` or beyond
    ``max_range_m``. ``correct_bias`` makes the estimator side undo the known slope/offset and
    the NLOS excess's mean, ``nlos_probability * nlos_bias_mean_m`` (a bias does not average
    out); without it ranges are used as they arrive.
    """

    data_file: str = "dwm1001_los_ranges.csv"
    noise_std_m: float | None = None
    nlos_probability: float = 0.05
    nlos_bias_mean_m: float = 0.4
    dropout_probability: float = 0.02
    max_range_m: float = 40.0
    correct_bias: bool = True

    def __post_init__(self) -> None:
        if not isinstance(self.data_file, str) or not self.data_file:
            raise ConfigError("data_file", self.data_file, "must be a non-empty file name or path")
        if self.noise_std_m is not None:
            self._non_negative("noise_std_m")
        self._probability("nlos_probability", "dropout_probability")
        self._non_negative("nlos_bias_mean_m")
        self._positive("max_range_m")
        if not isinstance(self.correct_bias, bool):
            raise ConfigError("correct_bias", self.correct_bias, "must be a bool")


@dataclass(frozen=True)
class CalibrationConfig(ConfigBase):
    """A calibration round: every anchor initiates in turn to every other anchor.

    ``measurements_per_pair`` (K) SS-TWR exchanges per ordered pair. The round's duration is
    ``n * (n - 1) * (pair_idle_s + K * exchange_s)``: as in the reference firmware, every pair
    ends with an ``F`` broadcast and its RX timeout (``sim.calibration_round``). The two
    constants are fitted (exactly, two equations, two unknowns) to ``reference_latencies_s``
    measured with ``reference_n_anchors`` anchors: the paper's 0.9 s at K=5 and 2.5 s at K=50
    for 4 anchors (60 ms idle and 2.96 ms per exchange).
    """

    measurements_per_pair: int = 5
    reference_n_anchors: int = 4
    reference_latencies_s: tuple[tuple[int, float], ...] = ((5, 0.9), (50, 2.5))

    def __post_init__(self) -> None:
        self._integer("measurements_per_pair", 1, 10_000)
        self._integer("reference_n_anchors", 2)
        refs = self.reference_latencies_s
        ok = (
            isinstance(refs, tuple)
            and len(refs) == 2
            and all(len(r) == 2 and r[0] > 0 and r[1] > 0 for r in refs)
            and refs[0][0] != refs[1][0]
        )
        if not ok:
            raise ConfigError(
                "reference_latencies_s", refs, "must be two (K, seconds) pairs with distinct K > 0"
            )


@dataclass(frozen=True)
class SimConfig(ConfigBase):
    """The whole simulated world: anchors, tags, motion, drift, ranging, calibration rounds.

    Anchors start near the corners of a square area of side ``area_size_m`` (with jitter of
    ``anchor_jitter_fraction`` of the side); tags start inside the anchors' polygon. In 3D the
    robots fly/drive at fixed heights drawn in ``[0, area_height_m]``. By default anchors and
    tags both follow the paper's constant-heading model with noise.
    """

    n_anchors: int = 4
    n_tags: int = 3
    dim: int = 2
    dt_s: float = 0.2
    area_size_m: float = 10.0
    area_height_m: float = 3.0
    anchor_jitter_fraction: float = 0.1
    # A team built for localization keeps its formation around the work area and its tags
    # inside it (see MotionConfig); free motion ("heading") is the named stress scenario
    # training/scenarios/free_motion.yml, where anchors can drift into near-collinear clusters
    # and tags leave their hull (mirror ambiguities by construction).
    anchor_motion: MotionConfig = field(default_factory=lambda: MotionConfig(model="patrol"))
    tag_motion: MotionConfig = field(default_factory=lambda: MotionConfig(model="inside_hull"))
    odometry: OdometryConfig = field(default_factory=OdometryConfig)
    ranging: RangingConfig = field(default_factory=RangingConfig)
    calibration: CalibrationConfig = field(default_factory=CalibrationConfig)
    # 3D: each anchor robot knows its antenna's mount height to this std (measured once; the
    # robots keep their heights), and every calibration uses it: the first one fixes the frame
    # on the heights (a yaw-only alignment), team rounds solve the plane on the ranges'
    # horizontal parts, relocations take the height as a prior. None: the ranges alone decide
    # the heights (four anchors at similar heights fix them only weakly).
    known_heights_std_m: float | None = None

    def __post_init__(self) -> None:
        self._integer("dim", 2, 3)
        self._integer("n_anchors", self.dim + 1, 256)
        self._integer("n_tags", 0, 10_000)
        self._positive("dt_s", "area_size_m", "area_height_m")
        if self.known_heights_std_m is not None:
            self._positive("known_heights_std_m")
            if self.dim != 3:
                raise ConfigError("known_heights_std_m", self.known_heights_std_m, "needs dim=3")
        if not 0.0 <= self._finite("anchor_jitter_fraction") < 0.5:
            raise ConfigError(
                "anchor_jitter_fraction", self.anchor_jitter_fraction, "must be in [0, 0.5)"
            )


TRIGGERS = ("any", "majority", "all")
ACTION_MODES = ("calibrate", "calibrate_and_move", "per_anchor")
TAG_FALLBACKS = ("hold", "predict")


@dataclass(frozen=True)
class SolverConfig(ConfigBase):
    """How the embedded localization backend solves calibrations and tag fixes.

    ``gauge`` places later calibrations in the running frame (``anchor0``: the paper's rule,
    anchor 0 keeps its on-board estimate; ``prior``: rigid fit to all anchors' estimates).
    ``loss`` is the robust loss (``linear``, ``huber``, ``soft_l1``, ``cauchy``, ``nlos``) for both;
    its scale is ``f_scale_sigmas`` range stds in calibrations and ``tag_f_scale_sigmas`` in tag
    fixes, where a residual is scaled by the range's std and the anchor's predicted error along
    the line of sight (``use_anchor_covariance``). That predicted error carries the frame's
    uncertainty as well as the shape's (about 4x the shape's error variance on the default
    scenario), while a tag is placed relative to the anchors: a stale anchor's biased range lies
    within 3 of those stds and is taken for noise; below one it is down-weighed. 0.7 was chosen
    on the suite's validation seeds (``benchmarks/bench_departures.py --only-tracker``; 3.0
    before) with the default Huber loss: IQM tag error 8.6 % lower on the default scenario's
    test seeds, better on 8 of 12 scenarios, worse beyond the CI on none. The other losses read
    the same scale; it was not tuned for them.
    """

    gauge: str = "prior"
    loss: str = "huber"
    f_scale_sigmas: float = 3.0
    tag_f_scale_sigmas: float = 0.7
    tag_iterations: int = 2
    use_anchor_covariance: bool = True
    # A tracked tag whose fix residual exceeds this is re-solved from the closed form.
    tag_restart_residual_m: float = 0.3

    def __post_init__(self) -> None:
        self._choice("gauge", ("anchor0", "prior"))
        self._choice("loss", ("linear", "huber", "soft_l1", "cauchy", "nlos"))
        self._positive("f_scale_sigmas", "tag_f_scale_sigmas")
        self._integer("tag_iterations", 1, 100)
        self._positive("tag_restart_residual_m")


@dataclass(frozen=True)
class EnvConfig(ConfigBase):
    """The calibration-scheduling task built on the simulator.

    Reward per step (team reward, shared by all anchors), all terms documented in the env:
    ``-(tag_error_weight * mean tag error [m] + anchor_error_weight * mean anchor error [m]
    + calibration_time_weight * fraction of the step spent calibrating
    + calibration_start_cost * [a round started this step])``.
    """

    sim: SimConfig = field(default_factory=SimConfig)
    solver: SolverConfig = field(default_factory=SolverConfig)
    max_cycles: int = 500
    trigger: str = "any"
    action_mode: str = "calibrate"
    move_speed_mps: float = 0.4
    move_headings: int = 8
    tag_fallback: str = "hold"
    residual_window_steps: int = 10
    tag_error_weight: float = 1.0
    anchor_error_weight: float = 0.0
    calibration_time_weight: float = 0.1
    calibration_start_cost: float = 0.0
    error_cap_m: float = 10.0

    def __post_init__(self) -> None:
        self._integer("max_cycles", 1)
        self._choice("trigger", TRIGGERS)
        self._choice("action_mode", ACTION_MODES)
        self._non_negative("move_speed_mps")
        self._integer("move_headings", 1, 64)
        self._choice("tag_fallback", TAG_FALLBACKS)
        self._integer("residual_window_steps", 1, 10_000)
        self._non_negative(
            "tag_error_weight", "anchor_error_weight", "calibration_time_weight", "calibration_start_cost"
        )
        self._positive("error_cap_m")
