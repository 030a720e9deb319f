"""Calibration rounds of many copies that started on the same step, simulated together.

Copies of the batched env that start a team round on the same step share its schedule (same
team size, K and start time), so their exchanges can be drawn in one call per step instead of
one :class:`~uwb_env.sim.calibration_round.CalibrationRound` per copy. The exchanges, the
interpolation of positions within a step and the per-pair aggregation are those of
``CalibrationRound`` and ``RangeMatrix.from_samples`` (tested against them).
"""

from __future__ import annotations

import numpy as np

from uwb_env.sim.calibration_round import CalibrationRound, RoundTiming
from uwb_env.sim.round_path import pair_mean_times_s


class RoundCohort(CalibrationRound):
    """Team rounds of the copies ``copies`` (C,), all started at ``start_time_s``: a
    :class:`CalibrationRound` whose ranges are (C, exchanges); ``advance`` takes (C, N, dim)
    positions of the cohort's copies."""

    def __init__(self, copies: np.ndarray, n_anchors: int, timing: RoundTiming, measurements_per_pair: int,
                 start_time_s: float):
        super().__init__(n_anchors, timing, measurements_per_pair, start_time_s)
        self.copies = np.asarray(copies, dtype=int)
        self.k = measurements_per_pair
        self.ranges_m = np.full((len(self.copies), len(self.times_s)), np.nan)

    def pair_statistics(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per copy and ordered pair: raw mean, sample std (ddof 1, 0 for one sample) and count,
        (C, N, N) each (NaN mean/std where no exchange got through), as ``RangeMatrix.from_samples``."""
        c, n, k = len(self.copies), self.n_anchors, self.k
        # the schedule runs the K exchanges of each ordered pair back to back
        block = self.ranges_m.reshape(c, n * (n - 1), k)
        ok = np.isfinite(block)
        count = ok.sum(2)
        with np.errstate(divide="ignore", invalid="ignore"):
            mean = np.where(ok, block, 0.0).sum(2) / count
            sq = np.where(ok, (block - mean[..., None]) ** 2, 0.0).sum(2)
            std = np.sqrt(sq / np.maximum(count - 1, 1))
        mean[count == 0] = np.nan
        std[count == 0] = np.nan
        i, j = self.initiator[::k], self.responder[::k]
        out_mean, out_std = np.full((c, n, n), np.nan), np.full((c, n, n), np.nan)
        out_count = np.zeros((c, n, n), dtype=int)
        out_mean[:, i, j], out_std[:, i, j], out_count[:, i, j] = mean, std, count
        return out_mean, out_std, out_count

    def pair_mean_times_s(self) -> np.ndarray:
        """(N, N) mean scheduled time of each ordered pair's exchanges (the diagonal 0)."""
        return pair_mean_times_s(self.n_anchors, self.times_s, self.initiator, self.responder)
