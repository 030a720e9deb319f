"""Odometry displacements on hardware: held back until their frame is known, then rotated into it.

The estimates live in the first calibration's paper frame; the robots' odometry reports in its
own frame, a rotation (and possibly a reflection) away that nothing tells in advance. Adding
the displacements as they come moves every estimate the wrong way as soon as the robots move.
:class:`OdometryFrameTracker` instead:

- holds the displacements back while the transform is unknown (the estimates stay where the
  last calibration put them) and counts each one's length as error of unknown direction in the
  predicted variance (:class:`HeldBackOdometry`), so tag fixes, the solver's priors and the
  scheduler's features see how stale the estimates are;
- after every applied team calibration fits one transform to the last ``max_intervals``
  calibration intervals (:func:`~uwb_env.localization.odometry_frame.fit_odometry_rotation_chain`:
  each interval with only its own odometry drift in its variance, the frame carried from one
  calibration to the next by each interval's alignment, a mirrored calibration included);
- applies it once the fit is ``ok`` at two calibrations in a row with the same answer (one
  chance ``ok`` among many fits is not enough), with the motion held back since the
  calibration's midpoint, and rotates every later displacement;
- checks each later interval against it and goes back to holding displacements when one
  contradicts it (a re-initialised odometry, the transform drifting with the odometry's heading).

A ``poor_fit`` drops the pooled intervals (a calibration or the odometry went wrong, or the
robots do not share one odometry frame, which this requires). Planar only.
"""

from __future__ import annotations

import numpy as np
from scipy.stats import chi2 as chi2_dist

from uwb_env.config import SimConfig
from uwb_env.localization.odometry_frame import (
    OdometryFrameFit,
    chained_chi2,
    fit_odometry_rotation_chain,
    planar_orthogonal,
    prepared_interval,
)
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
    are applied as they come). ``max_intervals``: how many of the latest calibration intervals
    one fit pools."""

    def __init__(self, config: SimConfig, mode: str = "estimate", margin_chi2: float = 16.0,
                 max_angle_std_deg: float = 5.0, max_intervals: int = 6):
        if mode not in ODOMETRY_FRAMES:
            raise ValueError(f"odometry_frame={mode!r}: expected one of {ODOMETRY_FRAMES}")
        if mode == "estimate" and config.dim != 2:
            raise ValueError(f"odometry_frame='estimate' with dim={config.dim}: the odometry frame's transform is "
                             "estimated in the plane only; give displacements in the calibration's frame "
                             "(odometry_frame='calibration')")
        self.config, self.mode = config, mode
        self.margin_chi2, self.max_angle_std_rad = margin_chi2, np.deg2rad(max_angle_std_deg)
        self.max_intervals = max_intervals
        self._drift = OdometryModel(config.odometry)  # drift since the last calibration

    def reset(self, odometry: HeldBackOdometry) -> None:
        n, dim = self.config.n_anchors, self.config.dim
        self.odometry = odometry
        # odometry frame -> current estimate frame; None while unknown
        self.rotation: np.ndarray | None = np.eye(dim) if self.mode == "calibration" else None
        self.fit: OdometryFrameFit | None = None  # the latest fit
        self.fits = 0
        self.reverted = 0  # transforms given up after later calibrations contradicted them
        self._last = None  # (positions, variance, cumulative odometry) at the last calibration's midpoint
        self._intervals: list = []  # consecutive (reference, later, displacement, variance) since the evidence began
        # an ok fit waiting for the next calibration's: its (angle, reflected, angle std) in the frame of
        # the calibration it was made at
        self._confirming: tuple | None = None
        self._drift.reset(n, np.random.default_rng(0))  # only its variance model is read
        self._times = [0.0]
        self._cumulative = [np.zeros((n, dim))]

    def step(self, time_s: float, moved: np.ndarray) -> np.ndarray:
        """One step's displacements (odometry frame) -> what to add to the estimates now."""
        if self.mode == "calibration":
            return moved
        self._times.append(float(time_s))
        self._cumulative.append(self._cumulative[-1] + moved)
        self._drift.note_motion(moved)
        if self.rotation is not None:
            return moved @ self.rotation.T
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
        if self.mode == "calibration":
            return np.zeros_like(positions)
        if not (np.isfinite(positions).all() and np.isfinite(var_m2).all()):
            # a solution without an honest covariance (e.g. a first calibration applied whatever
            # its verdict) is no evidence: start over from the next calibration
            self._last, self._intervals, self._confirming = None, [], None
            return np.zeros_like(positions)
        mid = 0.5 * (start_s + end_s)
        at_start, at_mid, at_end = (self._cumulative_at(t) for t in (start_s, mid, end_s))
        now = self._cumulative[-1]
        # drop the log before this round: later lookups start at its midpoint
        keep = max(int(np.searchsorted(self._times, start_s, side="right")) - 1, 0)
        self._times, self._cumulative = self._times[keep:], self._cumulative[keep:]
        # The round ranges its pairs one after another while the robots move; while the motion
        # is held back the carry to the midpoint does nothing: allow for the motion during the
        # round (uniform along each path: L^2 / 12, and the others' through the shared solve).
        # The paper frame's gauge gives anchor 0 no variance and the others its share: at least
        # the team's mean for each.
        moved2 = ((at_end - at_start) ** 2).sum(-1)
        var_m2 = np.asarray(var_m2, dtype=float)
        var = np.maximum(var_m2, var_m2.mean()) + (0.0 if self.rotation is not None else
                                                    (moved2 + moved2.mean()) / 12.0)
        last, self._last = self._last, (np.array(positions, dtype=float), var, at_mid)
        drift = self._drift.expected_drift_var_m2(2)
        self._drift.restart_drift()
        if last is None:
            return np.zeros_like(positions)
        interval = (last[0], self._last[0], at_mid - last[2], np.maximum(last[1] + var + drift, 1e-6))
        if self.rotation is not None:
            return self._monitor(interval)
        self.odometry.held_back[:] = now - at_mid  # the estimates are the solution at the midpoint
        self._intervals = (self._intervals + [interval])[-self.max_intervals:]
        self.fit = fit_odometry_rotation_chain(self._intervals, self.margin_chi2, self.max_angle_std_rad)
        self.fits += 1
        if self.fit.status == "poor_fit":  # a calibration or the odometry went wrong: start over from here
            self._intervals, self._confirming = [], None
            return np.zeros_like(positions)
        if not self.fit.ok:
            self._confirming = None
            return np.zeros_like(positions)
        # One ok is not enough: with a fit after every calibration, chance alone would pass one
        # now and then (and robots with odometry frames of their own sometimes fit one transform
        # over a single interval). Commit when the next calibration's fit, pooling the new
        # interval too, is ok again with the same handedness and angle.
        # Both are compared in the previous calibration's frame (the pooled window may have slid
        # since, so the two fits' first frames can differ).
        confirmed = False
        if self._confirming is not None and len(self._intervals) >= 2:
            earlier = [prepared_interval(*iv) for iv in self._intervals[:-1]]
            _, _, angle, hand = chained_chi2(np.array([self.fit.angle_rad]), self.fit.reflected, earlier)
            before_angle, before_reflected, before_std = self._confirming
            confirmed = (before_reflected == bool(hand[0]) and abs(np.angle(np.exp(1j * (angle[0] - before_angle))))
                         <= 3.0 * np.hypot(before_std, self.fit.angle_std_rad))
        if not confirmed:
            current = self.fit.current  # this fit's answer in this calibration's frame
            self._confirming = (float(np.arctan2(current[1, 0], current[0, 0])), bool(np.linalg.det(current) < 0),
                                self.fit.angle_std_rad)
            return np.zeros_like(positions)
        self.rotation = self.fit.current
        self.odometry.held_back[:] = 0.0
        self._intervals, self._confirming = [], None
        return (now - at_mid) @ self.rotation.T

    def anchor_calibration_applied(self, anchor: int, start_s: float, end_s: float) -> None:
        """A per-anchor round re-located ``anchor`` (no evidence on the transform: the others
        did not change): while displacements are held back, its estimate lacks the motion since
        the round's midpoint, which its predicted variance must count again."""
        if self.rotation is None:
            at_mid = self._cumulative_at(0.5 * (start_s + end_s))
            self.odometry.held_back[anchor] = self._cumulative[-1][anchor] - at_mid[anchor]

    def _monitor(self, interval) -> np.ndarray:
        """After the transform is known: each new interval must agree with it. The transform is
        carried into the frame the latest calibration was applied in; an interval that prefers
        another transform by the margin, or that the known one cannot explain, sends the
        tracker back to holding displacements (the motion already applied stays)."""
        reference, later, displacement, var = interval
        known = np.array(self.rotation)
        reflected = bool(np.linalg.det(known) < 0)
        angle = float(np.arctan2(known[1, 0], known[0, 0]))  # rot(a) or rot(a) diag(1, -1): the same column
        prepared = [prepared_interval(reference, later, displacement, var)]
        at_known, _, carried, hand = chained_chi2(np.array([angle]), reflected, prepared)
        free = fit_odometry_rotation_chain([interval], self.margin_chi2, self.max_angle_std_rad)
        dof = 2 * len(reference) - 3
        contradicted = (at_known[0] > chi2_dist.ppf(0.999, dof)
                        or (free.status in ("ok", "ambiguous") and at_known[0] - free.chi2 > self.margin_chi2))
        if contradicted:
            self.rotation = None
            self.reverted += 1
            self._intervals, self._confirming = [], None
            return np.zeros_like(reference)
        self.rotation = planar_orthogonal(float(carried[0]), bool(hand[0]))
        return np.zeros_like(reference)
