"""Measurement containers shared by the simulator, the solver and the hardware backend."""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

# A bias-corrected range can dip below zero next to an anchor (noise around a true ~0 m): that
# is a measurement. Far below zero it cannot be the corrected range of a real distance.
NEGATIVE_RANGE_TOLERANCE_M = 1.0
# A range carried along the odometry to another instant (``RangeMatrix.carry_var_m2``) adds the
# carry's error: this many of its standard deviations on top of the tolerance (a 64-anchor
# round takes minutes, and the carry's std grows to metres).
CARRY_TOLERANCE_SIGMAS = 5.0


def negative_range_floor_m(carry_var_m2=None):
    """The lowest corrected range (m) taken as a measurement: -NEGATIVE_RANGE_TOLERANCE_M, less
    CARRY_TOLERANCE_SIGMAS carry standard deviations where ranges were carried (array-shaped
    like ``carry_var_m2``; NaN carry variances count as none)."""
    if carry_var_m2 is None:
        return -NEGATIVE_RANGE_TOLERANCE_M
    carry = np.nan_to_num(np.asarray(carry_var_m2, dtype=float), nan=0.0, posinf=0.0)
    return -NEGATIVE_RANGE_TOLERANCE_M - CARRY_TOLERANCE_SIGMAS * np.sqrt(np.maximum(carry, 0.0))


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
        carry_var_m2: optional (n, n) variance added to each mean beyond its ranges' noise, not
            reduced by the count: the error of carrying the mean to another instant along the
            odometry (``RoundPath.carry_var_m2``). None: 0.
    """

    mean_m: np.ndarray
    std_m: np.ndarray
    count: np.ndarray
    carry_var_m2: np.ndarray | None = None

    def __post_init__(self):
        # Validated once here, so every consumer (solver, recorder, features) can trust it.
        from uwb_env.localization.errors import InvalidRangeError  # localization imports this module

        mean = np.asarray(self.mean_m, dtype=float)
        std = np.asarray(self.std_m, dtype=float)
        count = np.asarray(self.count)
        if mean.ndim != 2 or mean.shape[0] != mean.shape[1] or mean.shape[0] < 1:
            raise InvalidRangeError(f"RangeMatrix.mean_m: expected a square (n, n) matrix, got shape {mean.shape}")
        for name, array in (("std_m", std), ("count", count)):
            if array.shape != mean.shape:
                raise InvalidRangeError(f"RangeMatrix.{name}: shape {array.shape} does not match mean_m's {mean.shape}")
        if count.dtype.kind not in "iu":
            if count.dtype.kind not in "fb" or not np.all(np.isfinite(count)) or np.any(count != np.round(count)):
                raise InvalidRangeError("RangeMatrix.count: expected whole numbers of exchanges")
            count = count.astype(np.int64)
        if count.size and count.min() < 0:
            i, j = np.argwhere(count < 0)[0]
            raise InvalidRangeError(f"RangeMatrix.count[{i}, {j}] = {count[i, j]}: negative")
        measured = count > 0
        bad_mean = measured & ~np.isfinite(mean)
        if bad_mean.any():
            i, j = np.argwhere(bad_mean)[0]
            raise InvalidRangeError(
                f"RangeMatrix.mean_m[{i}, {j}] = {mean[i, j]!r} with count {count[i, j]}: not finite")
        bad_std = measured & ~(std >= 0) | (measured & np.isinf(std))
        if bad_std.any():
            i, j = np.argwhere(bad_std)[0]
            raise InvalidRangeError(f"RangeMatrix.std_m[{i}, {j}] = {std[i, j]!r}: must be finite and >= 0")
        if self.carry_var_m2 is not None:
            carry = np.asarray(self.carry_var_m2, dtype=float)
            if carry.shape != mean.shape:
                raise InvalidRangeError(
                    f"RangeMatrix.carry_var_m2: shape {carry.shape} does not match mean_m's {mean.shape}")
            bad_carry = measured & ~((carry >= 0) & np.isfinite(carry))
            if bad_carry.any():
                i, j = np.argwhere(bad_carry)[0]
                raise InvalidRangeError(
                    f"RangeMatrix.carry_var_m2[{i}, {j}] = {carry[i, j]!r}: must be finite and >= 0")
            object.__setattr__(self, "carry_var_m2", carry)
        object.__setattr__(self, "mean_m", mean)
        object.__setattr__(self, "std_m", std)
        object.__setattr__(self, "count", count)

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
        carry = self.carry_var_m2
        carry_ab = () if carry is None else (carry.ravel().take(upper), carry.ravel().take(lower))
        # NaN fails ">= floor"; inf fails "< inf"; each direction against its own floor (as the
        # general path's validation in calibrate_anchors)
        floor_a, floor_b = (negative_range_floor_m(c) for c in (carry_ab or (None, None)))
        above = bool((ma >= floor_a).all() and (mb >= floor_b).all())
        if not (np.minimum(ca, cb).min() > 0 and above and np.maximum(ma, mb).max() < np.inf):
            return None
        if std_m is not None:
            info_a, info_b = ca / std_m**2, cb / std_m**2
        else:
            if not min_std_m > 0:
                return None  # zero stds need the general path's special case
            std_flat = self.std_m.ravel()
            info_a = ca / np.maximum(std_flat.take(upper), min_std_m) ** 2
            info_b = cb / np.maximum(std_flat.take(lower), min_std_m) ** 2
        if not (info_a + info_b).min() > 0:  # NaN stds
            return None
        mean, var = combine_directions(ma, mb, info_a, info_b, *carry_ab)
        return pairs, mean, var

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
            carry = self.carry_var_m2
            carry_ab = () if carry is None else (carry.ravel().take(upper), carry.ravel().take(lower))
            mean, var = combine_directions(means[0], means[1], info[0], info[1], *carry_ab)
            # Pairs with valid data but zero std everywhere (min_std 0): plain average, variance 0.
            flat = (total == np.inf) | np.isnan(mean)
            if flat.any():
                k = valid.sum(axis=0)
                mean = np.where(flat, means.sum(axis=0) / np.maximum(k, 1), mean)
            var = np.where(total > 0, np.nan_to_num(var, nan=0.0, posinf=np.inf), np.inf)
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


def combine_directions(mean_a, mean_b, info_a, info_b, carry_a=None, carry_b=None):
    """(mean, variance) of unordered pairs from their two directions (arrays of any one shape):
    the inverse-variance weighted mean (``info``: count / sigma^2 of each direction's mean) and
    its variance 1 / (info_a + info_b), plus, given the directions' carry variances, those
    weighted as the means are (their carry errors taken as fully dependent, which this bounds
    from above; NaN carry counts as 0). The one place both directions are combined:
    :meth:`RangeMatrix.symmetric` and the batched envs' ``symmetric_arrays`` call it."""
    total = info_a + info_b
    mean = (info_a * mean_a + info_b * mean_b) / total
    var = 1.0 / total
    if carry_a is not None:
        var = var + (info_a * _nan_to_zero(carry_a) + info_b * _nan_to_zero(carry_b)) / total
    return mean, var


def _nan_to_zero(x: np.ndarray) -> np.ndarray:
    """np.nan_to_num(x) (NaN -> 0, +-inf -> the largest finite floats), with the usual case
    (NaN at most) in one call: nan_to_num costs ~10 us a call on a handful of pairs."""
    if np.isinf(x).any():
        return np.nan_to_num(x)
    return np.where(np.isnan(x), 0.0, x)


def pool_rounds(a: RangeMatrix, b: RangeMatrix) -> RangeMatrix:
    """Two rounds of the same anchors as one: per ordered pair, counts add, means are count-
    weighted and the std is the pooled sample std of all exchanges; carry variances are count-
    weighted as the means are (fully dependent: an upper bound)."""
    if a.mean_m.shape != b.mean_m.shape:
        from uwb_env.localization.errors import InvalidRangeError

        raise InvalidRangeError(f"pool_rounds: shapes {a.mean_m.shape} and {b.mean_m.shape} differ")
    ca, cb = a.count.astype(float), b.count.astype(float)
    count = ca + cb
    ma, mb = np.where(ca > 0, a.mean_m, 0.0), np.where(cb > 0, b.mean_m, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        mean = np.where(count > 0, (ca * ma + cb * mb) / count, np.nan)
        sa, sb = np.where(ca > 0, np.nan_to_num(a.std_m), 0.0), np.where(cb > 0, np.nan_to_num(b.std_m), 0.0)
        ss = (np.maximum(ca - 1, 0) * sa**2 + np.maximum(cb - 1, 0) * sb**2
              + ca * (ma - mean) ** 2 + cb * (mb - mean) ** 2)
        std = np.where(count > 0, np.sqrt(ss / np.maximum(count - 1, 1)), np.nan)
        carry = None
        if a.carry_var_m2 is not None or b.carry_var_m2 is not None:
            va = np.zeros_like(mean) if a.carry_var_m2 is None else np.where(ca > 0, a.carry_var_m2, 0.0)
            vb = np.zeros_like(mean) if b.carry_var_m2 is None else np.where(cb > 0, b.carry_var_m2, 0.0)
            carry = np.where(count > 0, (ca * va + cb * vb) / count, 0.0)
    return RangeMatrix(mean, std, count.astype(int), carry)
