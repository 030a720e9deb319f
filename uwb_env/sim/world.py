"""The simulated world: anchor robots, tags, odometry and UWB ranging.

Free of any RL API. Randomness comes only from the generator passed to :meth:`World.reset`.

Frames: true positions live in the *world* frame. The anchors' on-board estimates live in an
*estimate frame* (set by the localization backend after the first calibration, identity
before): ``p_est_frame = R @ (p_world - t)``. Odometry displacements are rotated into it.
"""

from __future__ import annotations

import numpy as np

from uwb_env.config import SimConfig
from uwb_env.sim.calibration_round import CalibrationRound, RoundTiming
from uwb_env.sim.motion import MotionModel
from uwb_env.sim.odometry import OdometryModel
from uwb_env.sim.ranging import RangeModel


class RoundRunner:
    """``run_calibration_round`` for anything with the World round interface (the simulated
    world and the hardware backend)."""

    def run_calibration_round(self, measurements_per_pair: int | None = None):
        """Start a round and step until it completes; return (RangeMatrix, steps taken)."""
        self.start_calibration_round(measurements_per_pair)
        steps = 0
        while not self.round.done:
            self.step()
            steps += 1
        return self.finish_calibration_round().result(), steps

    def calibration_applied(self, positions: np.ndarray, var_m2: np.ndarray, start_s: float, end_s: float) -> None:
        """A team calibration's solution was applied (the hardware backend fits its odometry
        frame from these; the simulator knows its frame)."""

    def anchor_calibration_applied(self, anchor: int, start_s: float, end_s: float) -> None:
        """Anchor ``anchor`` was re-located by a round from ``start_s`` to ``end_s`` (its estimate
        is the solution at the midpoint plus the odometry since)."""


def formation_xy(config: SimConfig, rng: np.random.Generator, copies: int | None = None) -> np.ndarray:
    """Initial anchor positions in the plane, (n, 2), or (copies, n, 2) for the batched env (the
    same draws in the same order for one copy): spread around the area's border (corners first
    for n = 4), counter-clockwise, with a uniform jitter."""
    n, size = config.n_anchors, config.area_size_m
    angles = 2 * np.pi * np.arange(n) / n + np.pi / 4 + np.pi
    radius = 0.5 * size * np.sqrt(2) * 0.8
    xy = size / 2 + radius * np.column_stack([np.cos(angles), np.sin(angles)])
    shape = (n, 2) if copies is None else (copies, n, 2)
    return np.clip(xy + config.anchor_jitter_fraction * size * rng.uniform(-1, 1, shape), 0.0, size)


def tags_inside(anchors_xy: np.ndarray, n_tags: int, rng: np.random.Generator) -> np.ndarray:
    """Tags as convex combinations of the anchors (inside their polygon, the paper's setup):
    (n_tags, 2) for (n, 2) anchors, or (copies, n_tags, 2) for (copies, n, 2)."""
    n = anchors_xy.shape[-2]
    size = n_tags if anchors_xy.ndim == 2 else (anchors_xy.shape[0], n_tags)
    return rng.dirichlet(np.ones(n), size) @ anchors_xy


class World(RoundRunner):
    """N anchor robots with drifting odometry and M tags in a square area.

    Args:
        config: the simulation configuration.
        range_model: optional pre-built range model (fitting is done once and shared).
    """

    def __init__(self, config: SimConfig | None = None, range_model: RangeModel | None = None):
        self.config = config or SimConfig()
        cfg = self.config
        self.range_model = range_model or RangeModel(cfg.ranging)
        self.timing = RoundTiming.fit(cfg.calibration)
        # One kernel moves anchors (rows :n_anchors) and tags (the rest) together.
        self.motion = MotionModel(
            [(cfg.anchor_motion, cfg.n_anchors), (cfg.tag_motion, cfg.n_tags)], cfg.area_size_m
        )
        self._n = cfg.n_anchors
        self.odometry = OdometryModel(cfg.odometry)
        self.dt_s = cfg.dt_s
        self.rng: np.random.Generator | None = None
        self.set_estimate_frame(np.eye(cfg.dim), np.zeros(cfg.dim))
        self.round: CalibrationRound | None = None

    # -- lifecycle -------------------------------------------------------------------------
    def reset(self, rng: np.random.Generator) -> None:
        """Place robots, draw per-episode parameters; estimates start at the truth."""
        cfg = self.config
        self.rng = rng
        self.time_s = 0.0
        self.step_count = 0
        anchors = self.initial_anchors(rng)
        self.motion.reset(np.vstack([anchors, self.initial_tags(anchors, rng)]), rng)
        self.odometry.reset(cfg.n_anchors, rng)
        # what each robot was told of its antenna's height (``known_heights_std_m``; drawn last so
        # that the option leaves every other draw where it was)
        std = cfg.known_heights_std_m
        self.known_heights_m = None if std is None else anchors[:, 2] + std * rng.standard_normal(cfg.n_anchors)
        self.set_estimate_frame(np.eye(cfg.dim), np.zeros(cfg.dim))
        self.anchors_est = anchors.copy()
        self.round = None

    @property
    def anchors_true(self) -> np.ndarray:
        return self.motion.positions[: self._n]

    @property
    def tags_true(self) -> np.ndarray:
        return self.motion.positions[self._n :]

    def step(self) -> None:
        """Advance one ``dt_s``: move robots, drift estimates, progress a running round."""
        rng = self.rng
        n = self._n
        before = self.motion.positions[:n].copy() if self.round is not None else None
        delta, turn = self.motion.step(self.dt_s, rng)
        odo = self.odometry.estimated_displacement(delta[:n], turn[:n], self.dt_s, rng)
        self.anchors_est += odo if self._identity_frame else odo @ self.frame_rotation.T
        t0 = self.time_s
        self.step_count += 1
        self.time_s = self.step_count * self.dt_s
        if self.round is not None:
            self.round.advance(t0, self.time_s, before, self.motion.positions[:n], self.range_model, rng)

    # -- measurements ----------------------------------------------------------------------
    def measure_tag_ranges(self) -> np.ndarray:
        """Raw anchor-to-tag ranges (n_anchors, n_tags) at the current positions; NaN = lost."""
        pos = self.motion.positions
        if self.config.dim == 2:  # complex |a - t| is two numpy calls instead of four
            z = pos.view(np.complex128)[:, 0]
            return self.range_model.measure(np.abs(z[: self._n, None] - z[None, self._n :]), self.rng)
        diff = pos[: self._n, None, :] - pos[None, self._n :, :]
        return self.range_model.measure(np.sqrt((diff * diff).sum(-1)), self.rng)

    def start_calibration_round(self, measurements_per_pair: int | None = None, initiators=None) -> CalibrationRound:
        """Begin a round at the current time; :meth:`step` fills it until ``round.done``.
        ``initiators``: e.g. ``[i]`` for a per-anchor round (default: the team round)."""
        k = measurements_per_pair or self.config.calibration.measurements_per_pair
        self.round = CalibrationRound(self.config.n_anchors, self.timing, k, self.time_s, initiators)
        return self.round

    def finish_calibration_round(self) -> CalibrationRound:
        """Detach and return the (done) round."""
        if self.round is None or not self.round.done:
            raise RuntimeError("no finished calibration round to collect")
        finished, self.round = self.round, None
        return finished


    # -- frames ----------------------------------------------------------------------------
    def set_estimate_frame(self, rotation: np.ndarray, origin: np.ndarray) -> None:
        """Declare the frame the anchors' estimates are expressed in."""
        self.frame_rotation = np.asarray(rotation, dtype=float)
        self.frame_origin = np.asarray(origin, dtype=float)
        self._identity_frame = bool(np.array_equal(self.frame_rotation, np.eye(self.config.dim)))

    def to_estimate_frame(self, points_world: np.ndarray) -> np.ndarray:
        return (points_world - self.frame_origin) @ self.frame_rotation.T

    def anchor_errors_m(self) -> np.ndarray:
        """Per-anchor distance between on-board estimate and truth (estimate frame)."""
        return np.linalg.norm(self.anchors_est - self.to_estimate_frame(self.anchors_true), axis=1)

    # -- placement -------------------------------------------------------------------------
    @property
    def tag_correction(self) -> RangeModel:
        """The bias model the estimator undoes on tag ranges (the hardware world: per firmware)."""
        return self.range_model

    @property
    def round_correction(self) -> RangeModel:
        """The bias model the estimator undoes on calibration-round ranges."""
        return self.range_model

    def initial_anchors(self, rng: np.random.Generator) -> np.ndarray:
        cfg = self.config
        xy = formation_xy(cfg, rng)
        if cfg.dim == 3:
            # Ranges fix the third coordinate only as far as the anchors leave one plane: a 3D
            # deployment mounts them at clearly different heights. Heights are redrawn until the
            # anchors' thickness off their best plane is at least a fifth of the height range.
            for _ in range(100):
                anchors = self._with_height(xy, rng)
                centred = anchors - anchors.mean(0)
                if np.linalg.svd(centred, compute_uv=False)[-1] >= 0.2 * cfg.area_height_m:
                    break
            return anchors
        return self._with_height(xy, rng)

    def initial_tags(self, anchors: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        return self._with_height(tags_inside(anchors[:, :2], self.config.n_tags, rng), rng)

    def _with_height(self, xy: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        if self.config.dim == 2:
            return xy
        z = rng.uniform(0.0, self.config.area_height_m, (len(xy), 1))
        return np.hstack([xy, z])
