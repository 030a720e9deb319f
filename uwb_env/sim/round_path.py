"""What the robots believed about their own motion through a calibration round.

A round's pairs are ranged one after another while the robots move (a 4-anchor round lasts
about a second, a 16-anchor one several), so the matrix mixes geometries. The solution is
placed at the round's midpoint: every pair's mean range is carried from its exchange time to
the midpoint along the on-board estimates, the solver's prior is the estimate at the midpoint,
and the estimate after the round is the solution plus the odometry since the midpoint. All
three need the estimated *path*, not its two ends: robots that turn or stop mid-round (patrol
waypoints, stop-and-go, commanded motion) are not where a straight line between the ends puts
them. ``RoundPath`` records the estimates (and the odometry's drift accumulators, so that the
drift since the midpoint stays predicted) at every step boundary of a round, for one team
(``(N, dim)`` estimates) or a cohort of batched copies (``(C, N, dim)``): one implementation for
both envs.
"""

from __future__ import annotations

import numpy as np

from uwb_env.sim._round_path_kernel import interpolate


class RoundPath:
    """Estimates at each step boundary since ``time_s`` (the round's start).

    Args:
        time_s: start time.
        estimates: (..., N, dim) on-board anchor estimates at the start.
        drift: the odometry's accumulators then (``OdometryModel.snapshot``), or None.
        truth: (..., N, dim) true positions (simulation only; the first calibration's frame
            alignment), or None.
    """

    def __init__(self, time_s: float, estimates: np.ndarray, drift: dict | None = None,
                 truth: np.ndarray | None = None):
        self.times_s = [float(time_s)]
        self.estimates = [np.array(estimates, dtype=float)]
        self.drifts = [drift]
        self.truths = None if truth is None else [np.array(truth, dtype=float)]
        self._midpoint = None  # midpoint_estimates, kept until the next record

    def record(self, time_s: float, estimates: np.ndarray, drift: dict | None = None,
               truth: np.ndarray | None = None) -> None:
        """One more step boundary (call after every world step while the round runs)."""
        self.times_s.append(float(time_s))
        self.estimates.append(np.array(estimates, dtype=float))
        self.drifts.append(drift)
        self._midpoint = None
        if self.truths is not None:
            self.truths.append(np.array(truth, dtype=float))

    @property
    def midpoint_time_s(self) -> float:
        return 0.5 * (self.times_s[0] + self.times_s[-1])

    def _at(self, series: list[np.ndarray] | np.ndarray, t: np.ndarray) -> np.ndarray:
        """series (one array per boundary, or stacked) linearly interpolated at times t (any
        shape) -> (*t.shape, ...)."""
        if len(self.times_s) == 1:
            return np.broadcast_to(series[0], (*np.shape(t), *series[0].shape)).copy()
        stack = series if isinstance(series, np.ndarray) else np.array(series)
        out = interpolate(np.asarray(self.times_s), stack.reshape(len(stack), -1),
                          np.ascontiguousarray(t, dtype=float).reshape(-1))
        return out.reshape(np.shape(t) + stack.shape[1:])

    def midpoint_estimates(self) -> np.ndarray:
        """(..., N, dim) the estimates at the round's midpoint (a new array per call)."""
        if self._midpoint is None:  # read by the solve's prior and by carry: interpolated once
            self._midpoint = self._at(self.estimates, np.asarray(self.midpoint_time_s))
        return self._midpoint.copy()

    def midpoint_truth(self) -> np.ndarray:
        if self.truths is None:
            raise ValueError("RoundPath: no true positions were recorded")
        return self._at(self.truths, np.asarray(self.midpoint_time_s))

    def midpoint_drift(self) -> dict | None:
        """The drift accumulators at the step boundary nearest the midpoint (within half a step:
        the odometry between boundaries is not observed)."""
        k = int(np.argmin(np.abs(np.asarray(self.times_s) - self.midpoint_time_s)))
        return self.drifts[k]

    def carry(self, mean_m: np.ndarray, pair_times_s: np.ndarray | None) -> np.ndarray:
        """(..., N, N) per ordered pair mean ranges carried to the midpoint geometry: each pair's
        range minus the change of its estimated distance between its mean exchange time
        (``pair_times_s`` (N, N), absolute) and the midpoint. Without exchange times (hardware
        rounds report only the matrix) or a round of no duration: unchanged."""
        if pair_times_s is None or self.times_s[-1] <= self.times_s[0]:
            return mean_m
        n = mean_m.shape[-1]
        i, j = np.nonzero(~np.eye(n, dtype=bool))
        # (P, ..., N, dim) estimates at each pair's time -> the two ends' positions (P, ..., dim)
        at_pair = self._at(self.estimates, pair_times_s[i, j])
        mid = self.midpoint_estimates()
        p = np.arange(len(i))
        d_pair = np.linalg.norm(at_pair[p, ..., i, :] - at_pair[p, ..., j, :], axis=-1)  # (P, ...)
        d_mid = np.linalg.norm(mid[..., i, :] - mid[..., j, :], axis=-1)  # (..., P)
        out = np.array(mean_m, dtype=float, copy=True)
        out[..., i, j] -= np.moveaxis(d_pair, 0, -1) - d_mid
        return out

    def carry_var_m2(self, pair_times_s: np.ndarray | None, odometry) -> np.ndarray | None:
        """(..., N, N) variance :meth:`carry` adds to each ordered pair's mean: the change of the
        estimated distance stands in for the true one, so the odometry's drift between the
        pair's time and the midpoint enters the carried range, along the pair. Per end: the
        drift's variance over its axes (dim; 2 for planar odometry, projected on the pair's
        horizontal part in 3D), the two ends independent. The drift variance is the odometry
        model's (``drift_var_between``) from the step boundary nearest the midpoint to each
        boundary, linear in time between boundaries. None where :meth:`carry` leaves the means
        unchanged or no drift was recorded."""
        if pair_times_s is None or self.times_s[-1] <= self.times_s[0] or self.drifts[0] is None:
            return None
        shape = self.estimates[0].shape  # (..., N, dim)
        n, dim = shape[-2], shape[-1]
        k_mid = int(np.argmin(np.abs(np.asarray(self.times_s) - self.midpoint_time_s)))
        # every boundary at once: from the boundary to the midpoint before it, from the
        # midpoint to it after
        steps = np.arange(len(self.drifts))
        var = odometry.drift_var_series(self.drifts, np.minimum(steps, k_mid), np.maximum(steps, k_mid), dim=dim)
        var = var.reshape((len(self.drifts),) + shape[:-1])
        i, j = np.nonzero(~np.eye(n, dtype=bool))
        at_pair = self._at(var, pair_times_s[i, j])  # (P, ..., N)
        p = np.arange(len(i))
        pair_var = np.moveaxis(at_pair[p, ..., i] + at_pair[p, ..., j], 0, -1)  # (..., P)
        if odometry.planar:
            pair_var = pair_var / 2.0
            if dim == 3:  # only the pair direction's horizontal part sees the drift
                est = self.midpoint_estimates()
                u = est[..., i, :] - est[..., j, :]
                pair_var = pair_var * np.sum(u[..., :2] ** 2, axis=-1) / np.maximum(np.sum(u * u, axis=-1), 1e-24)
        else:
            pair_var = pair_var / dim
        out = np.zeros(shape[:-2] + (n, n))
        out[..., i, j] = pair_var
        return out


def pair_mean_times_s(n: int, times_s: np.ndarray, initiator: np.ndarray, responder: np.ndarray) -> np.ndarray:
    """(N, N) mean scheduled time of each ordered pair's exchanges (0 where none)."""
    total, count = np.zeros((n, n)), np.zeros((n, n))
    np.add.at(total, (initiator, responder), times_s)
    np.add.at(count, (initiator, responder), 1.0)
    return total / np.maximum(count, 1.0)
