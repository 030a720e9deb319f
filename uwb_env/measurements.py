"""Measurement containers shared by the simulator, the solver and the hardware backend."""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np


@lru_cache(maxsize=64)
def _pair_index(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unordered pairs i < j of n anchors, and the flat indices of (i, j) and (j, i)."""
    iu, ju = np.triu_indices(n, 1)
    pairs = np.column_stack([iu, ju])
    upper, lower = iu * n + ju, ju * n + iu
    for shared in (pairs, upper, lower):
        shared.flags.writeable = False  # shared between calls: callers must not modify them
    return pairs, upper, lower


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

    def symmetric(
        self, min_std_m: float = 0.0, std_m: float | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Combine both directions of each unordered pair i < j.

        Args:
            min_std_m: floor on each direction's sample std.
            std_m: if given, a known std for every range, in place of the sample stds.

        Returns:
            (pairs (P, 2) int, mean (P,), variance of the mean (P,)), only pairs with data.
            The variance is max(std, min_std)^2 / count, pooled inverse-variance over both
            directions.
        """
        complete = self.complete_symmetric(min_std_m, std_m)
        return complete if complete is not None else self._symmetric_general(min_std_m, std_m)

    def complete_symmetric(
        self, min_std_m: float = 0.0, std_m: float | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """:meth:`symmetric` for the usual round, in a few array calls: every ordered pair
        measured, finite and >= 0 (and stds > 0 after the floor). None for anything else."""
        pairs, upper, lower = _pair_index(self.n_anchors)
        mean_flat, count_flat = self.mean_m.ravel(), self.count.ravel()
        ma, mb = mean_flat.take(upper), mean_flat.take(lower)
        ca, cb = count_flat.take(upper), count_flat.take(lower)
        # NaN propagates through minimum and fails ">= 0"; inf fails "< inf"
        if not (np.minimum(ca, cb).min() > 0 and np.minimum(ma, mb).min() >= 0 and np.maximum(ma, mb).max() < np.inf):
            return None
        if std_m is not None:
            info_a, info_b = ca / std_m**2, cb / std_m**2
        else:
            if not min_std_m > 0:
                return None  # zero stds need the general path's special case
            std_flat = self.std_m.ravel()
            info_a = ca / np.maximum(std_flat.take(upper), min_std_m) ** 2
            info_b = cb / np.maximum(std_flat.take(lower), min_std_m) ** 2
        total = info_a + info_b
        if not total.min() > 0:  # NaN stds
            return None
        return pairs, (info_a * ma + info_b * mb) / total, 1.0 / total

    def _symmetric_general(self, min_std_m: float, std_m: float | None):
        pairs, upper, lower = _pair_index(self.n_anchors)
        mean_flat, count_flat = self.mean_m.ravel(), self.count.ravel()
        means = np.stack([mean_flat.take(upper), mean_flat.take(lower)])
        counts = np.stack([count_flat.take(upper), count_flat.take(lower)]).astype(float)
        valid = (counts > 0) & np.isfinite(means)
        means = np.where(valid, means, 0.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            if std_m is not None:
                info = np.where(valid, counts, 0.0) / (std_m * std_m)
            else:
                std_flat = self.std_m.ravel()
                stds = np.maximum(np.stack([std_flat.take(upper), std_flat.take(lower)]), min_std_m)
                info = np.where(valid, counts / np.maximum(stds, 1e-12) ** 2, 0.0)
            total = info.sum(axis=0)
            mean = (info * means).sum(axis=0) / total
            # Pairs with valid data but zero std everywhere (min_std 0): plain average.
            flat = (total == np.inf) | np.isnan(mean)
            if flat.any():
                k = valid.sum(axis=0)
                mean = np.where(flat, means.sum(axis=0) / np.maximum(k, 1), mean)
            var = np.where(total > 0, 1.0 / total, np.inf)
        keep = valid.any(axis=0)
        if keep.all():
            return pairs, mean, var
        return pairs[keep], mean[keep], var[keep]

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
