"""Measurement containers shared by the simulator, the solver and the hardware backend."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class RangeMatrix:
    """Result of one calibration round, per *ordered* pair (initiator i, responder j).

    Attributes:
        mean_m: (n, n) mean range; NaN where no measurement arrived (and on the diagonal).
        std_m: (n, n) sample standard deviation of the K ranges (0 when K == 1).
        count: (n, n) number of ranges that arrived.
    """

    mean_m: np.ndarray
    std_m: np.ndarray
    count: np.ndarray

    @property
    def n_anchors(self) -> int:
        return self.mean_m.shape[0]

    def symmetric(self, min_std_m: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Combine both directions of each unordered pair i < j.

        Returns:
            (pairs (P, 2) int, mean (P,), variance of the mean (P,)), only pairs with data.
            The variance is max(std, min_std)^2 / count, pooled inverse-variance over both
            directions.
        """
        n = self.n_anchors
        iu, ju = np.triu_indices(n, 1)
        means = np.stack([self.mean_m[iu, ju], self.mean_m[ju, iu]])
        stds = np.maximum(np.stack([self.std_m[iu, ju], self.std_m[ju, iu]]), min_std_m)
        counts = np.stack([self.count[iu, ju], self.count[ju, iu]]).astype(float)
        valid = (counts > 0) & np.isfinite(means)
        with np.errstate(divide="ignore", invalid="ignore"):
            info = np.where(valid, counts / np.maximum(stds, 1e-12) ** 2, 0.0)
            total = info.sum(axis=0)
            mean = np.where(valid, means, 0.0)
            mean = (info * mean).sum(axis=0) / total
            # Pairs with valid data but zero std everywhere (min_std 0): plain average.
            flat = (total == np.inf) | np.isnan(mean)
            if flat.any():
                k = valid.sum(axis=0)
                plain = np.where(valid, means, 0.0).sum(axis=0) / np.maximum(k, 1)
                mean = np.where(flat, plain, mean)
            var = np.where(total > 0, 1.0 / total, np.inf)
        keep = valid.any(axis=0)
        return np.column_stack([iu, ju])[keep], mean[keep], var[keep]

    @staticmethod
    def from_samples(n: int, initiator: np.ndarray, responder: np.ndarray, ranges_m: np.ndarray):
        """Aggregate individual exchanges (NaN = lost) into per-pair mean/std/count."""
        ok = np.isfinite(ranges_m)
        idx = initiator[ok] * n + responder[ok]
        values = ranges_m[ok]
        count = np.bincount(idx, minlength=n * n).astype(float)
        total = np.bincount(idx, weights=values, minlength=n * n)
        with np.errstate(divide="ignore", invalid="ignore"):
            mean = total / count
            sq = np.bincount(idx, weights=(values - mean[idx]) ** 2, minlength=n * n)
            std = np.sqrt(sq / np.maximum(count - 1, 1))
        mean[count == 0] = np.nan
        std[count == 0] = np.nan
        return RangeMatrix(mean.reshape(n, n), std.reshape(n, n), count.reshape(n, n).astype(int))
