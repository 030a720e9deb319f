"""Odometry displacements on hardware: held back until their frame is known, then rotated into it.

The estimates live in the first calibration's paper frame; the robots' odometry reports in its
own frame, a rotation (and possibly a reflection) away that nothing tells in advance. Adding
the displacements as they come moves every estimate the wrong way as soon as the robots move.
:class:`OdometryFrameTracker` instead:

- holds the displacements back while the transform is unknown (the estimates stay where the
  last calibration put them) and counts each one's length as error of unknown direction in the
  predicted variance (:class:`HeldBackOdometry`), so tag fixes, the solver's priors and the
  scheduler's features see how stale the estimates are;
- after every applied team calibration fits the transform from the odometry between that
  calibration and a reference one (:func:`~uwb_env.localization.odometry_frame.fit_odometry_rotation`);
- once the fit is ``ok``, maps it into the current estimate frame (the calibrations since the
  reference were aligned to estimates that lacked the motion, so that frame may have turned),
  applies the motion held back since the calibration's midpoint and rotates every later
  displacement.

A fit that is ``poor_fit`` restarts from the latest calibration as the new reference;
``ambiguous`` and ``unobservable`` keep the reference so that the evidence accumulates with
the motion. Planar only. The odometry's own heading drift (the transform turning slowly) is
not tracked: a transform, once known, is kept.
"""

from __future__ import annotations

import numpy as np

from uwb_env.config import SimConfig
from uwb_env.localization.odometry_frame import OdometryFrameFit, fit_odometry_rotation
from uwb_env.sim.odometry import OdometryModel

ODOMETRY_FRAMES = ("estimate", "calibration")


class HeldBackOdometry(OdometryModel):
    """The odometry drift model plus displacements not applied to the estimates: ``held_back``
    (n, dim), each one an error of known length and unknown direction (variance |d|^2)."""

    def reset(self, n: int, rng: np.random.Generator, dim: int = 2) -> None:
        super().reset(n, rng)
        self.held_back = np.zeros((n, dim))

    def expected_drift_var_m2(self, dim: int = 2, robots=slice(None)) -> np.ndarray:
        held = (self.held_back[robots] ** 2).sum(-1)
        return super().expected_drift_var_m2(dim, robots) + held

    def restart_drift(self, robots=slice(None), since: dict | None = None) -> None:
        super().restart_drift(robots, since)
        self.held_back[robots] = 0.0


class OdometryFrameTracker:
    """See the module docstring. ``mode``: ``"estimate"`` (learn the transform) or
    ``"calibration"`` (the source already reports in the calibration's frame: displacements
    are applied as they come)."""

    def __init__(self, config: SimConfig, mode: str = "estimate", margin_chi2: float = 16.0,
                 max_angle_std_deg: float = 5.0):
        if mode not in ODOMETRY_FRAMES:
            raise ValueError(f"odometry_frame={mode!r}: expected one of {ODOMETRY_FRAMES}")
        if mode == "estimate" and config.dim != 2:
            raise ValueError(f"odometry_frame='estimate' with dim={config.dim}: the odometry frame's transform is "
                             "estimated in the plane only; give displacements in the calibration's frame "
                             "(odometry_frame='calibration')")
        self.config, self.mode = config, mode
        self.margin_chi2, self.max_angle_std_rad = margin_chi2, np.deg2rad(max_angle_std_deg)
        self._drift = OdometryModel(config.odometry)  # drift since the reference calibration

    def reset(self, odometry: HeldBackOdometry) -> None:
        n, dim = self.config.n_anchors, self.config.dim
        self.odometry = odometry
        # odometry frame -> current estimate frame; None while unknown
        self.rotation: np.ndarray | None = np.eye(dim) if self.mode == "calibration" else None
        self.fit: OdometryFrameFit | None = None  # the latest fit
        self.fits = 0
        self._reference = None  # (positions, variance, cumulative odometry) at a calibration's midpoint
        self._drift.reset(n, np.random.default_rng(0))  # only its variance model is read
        self._times = [0.0]
        self._cumulative = [np.zeros((n, dim))]

    def step(self, time_s: float, moved: np.ndarray) -> np.ndarray:
        """One step's displacements (odometry frame) -> what to add to the estimates now."""
        if self.rotation is not None:
            return moved @ self.rotation.T
        self._times.append(float(time_s))
        self._cumulative.append(self._cumulative[-1] + moved)
        self._drift.note_motion(moved)
        self.odometry.held_back += moved
        return np.zeros_like(moved)

    def _cumulative_at(self, t: float) -> np.ndarray:
        times = np.asarray(self._times)
        stack = np.asarray(self._cumulative)
        flat = stack.reshape(len(times), -1)
        return np.array([np.interp(t, times, col) for col in flat.T]).reshape(stack.shape[1:])

    def calibration_applied(self, positions: np.ndarray, var_m2: np.ndarray, start_s: float,
                            end_s: float) -> np.ndarray:
        """A team calibration was applied: ``positions`` (N, 2) at its round's midpoint in the
        estimate frame, ``var_m2`` (N,) their variances (trace); the round ran from ``start_s``
        to ``end_s``. Returns the correction to add to the estimates now (zero unless the
        transform was just decided: then the motion held back since the midpoint)."""
        if self.rotation is not None:
            return np.zeros_like(positions)
        mid = 0.5 * (start_s + end_s)
        at_start, at_mid, at_end = (self._cumulative_at(t) for t in (start_s, mid, end_s))
        now = self._cumulative[-1]
        self.odometry.held_back[:] = now - at_mid  # the estimates are the solution at the midpoint
        # The round ranges its pairs one after another while the robots move, and with the
        # estimates held still the carry to the midpoint does nothing: allow for the motion
        # during the round (uniform along each path: L^2 / 12, and the others' through the solve).
        moved2 = ((at_end - at_start) ** 2).sum(-1)
        # the paper frame's gauge gives anchor 0 no variance and the others its share: at least
        # the team's mean for each
        var_m2 = np.asarray(var_m2, dtype=float)
        var = np.maximum(var_m2, var_m2.mean()) + (moved2 + moved2.mean()) / 12.0
        if self._reference is None:
            self._set_reference(positions, var, at_mid)
            return np.zeros_like(positions)
        ref_positions, ref_var, ref_cumulative = self._reference
        total = ref_var + var + self._drift.expected_drift_var_m2(2)
        self.fit = fit_odometry_rotation(ref_positions, positions, at_mid - ref_cumulative, np.maximum(total, 1e-6),
                                         self.margin_chi2, self.max_angle_std_rad)
        self.fits += 1
        if self.fit.status == "poor_fit":  # a calibration or the odometry went wrong: start over from here
            self._set_reference(positions, var, at_mid)
        if not self.fit.ok:
            return np.zeros_like(positions)
        # the fit maps into the reference's frame; the current one is its alignment away
        self.rotation = self.fit.alignment @ self.fit.rotation
        self.odometry.held_back[:] = 0.0
        self._times, self._cumulative = [], []
        return (now - at_mid) @ self.rotation.T

    def _set_reference(self, positions, var, cumulative) -> None:
        self._reference = (np.array(positions, dtype=float), np.array(var, dtype=float), cumulative)
        self._drift.restart_drift()
