"""Per-episode statistics with 95 % bootstrap confidence intervals (Agarwal et al. 2021).

Everything takes one value per episode (e.g. the episode's mean tag error); comparisons are
paired by seed (element i of both arrays comes from the same seed and scenario). Bootstraps are
``scipy.stats.bootstrap`` (BCa where the statistic is smooth enough, percentile otherwise),
proportions use the Wilson interval of ``scipy.stats.binomtest``. Lower error is better.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy import stats

CATASTROPHIC_M = 1.0  # an episode whose mean tag error exceeds this is a localization failure
CONFIDENCE = 0.95
N_RESAMPLES = 2000


@dataclass(frozen=True)
class Estimate:
    """A point estimate with its confidence interval (``ci_low`` <= ``value`` <= ``ci_high``
    usually, not always for BCa on tiny samples)."""

    value: float
    ci_low: float
    ci_high: float
    n: int

    def covers(self, x: float) -> bool:
        return self.ci_low <= x <= self.ci_high

    def excludes_zero(self) -> bool:
        """The verdict rule: a difference is significant when its CI excludes zero."""
        return not self.covers(0.0)

    def to_dict(self) -> dict:
        return asdict(self)


def iqm(x: np.ndarray, axis: int = -1) -> np.ndarray:
    """Interquartile mean: the mean of the middle 50 % (``scipy.stats.trim_mean`` at 25 %)."""
    return stats.trim_mean(x, 0.25, axis=axis)


def _median(x, axis=-1):
    return np.median(x, axis=axis)


def _mean(x, axis=-1):
    return np.mean(x, axis=axis)


STATISTICS = {"iqm": iqm, "median": _median, "mean": _mean}


def _as_1d(name: str, x) -> np.ndarray:
    a = np.asarray(x, dtype=float).ravel()
    if a.size == 0 or not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: needs a non-empty array of finite values, got {a.size} values")
    return a


def _rng(seed):
    return np.random.default_rng(seed)


def bootstrap_ci(x, statistic: str = "iqm", seed: int | None = 0, n_resamples: int = N_RESAMPLES) -> Estimate:
    """``statistic`` ("iqm", "median" or "mean") of ``x`` with its bootstrap CI."""
    if statistic not in STATISTICS:
        raise ValueError(f"statistic={statistic!r}: one of {sorted(STATISTICS)}")
    a = _as_1d("x", x)
    fn = STATISTICS[statistic]
    value = float(fn(a))
    if a.size < 2 or np.ptp(a) == 0:
        return Estimate(value, value, value, a.size)
    # The median's bootstrap distribution is lumpy: BCa's jackknife acceleration misbehaves on it.
    method = "percentile" if statistic == "median" else "BCa"
    res = stats.bootstrap((a,), fn, n_resamples=n_resamples, confidence_level=CONFIDENCE, method=method,
                          vectorized=True, axis=-1, random_state=_rng(seed))
    low, high = res.confidence_interval
    return Estimate(value, float(low), float(high), a.size)


def catastrophic_rate(x, threshold_m: float = CATASTROPHIC_M) -> Estimate:
    """Fraction of episodes whose error exceeds ``threshold_m``, with a Wilson 95 % interval."""
    a = _as_1d("x", x)
    k = int(np.count_nonzero(a > threshold_m))
    ci = stats.binomtest(k, a.size).proportion_ci(confidence_level=CONFIDENCE, method="wilson")
    return Estimate(k / a.size, float(ci.low), float(ci.high), a.size)


def summarize_errors(x, seed: int | None = 0) -> dict[str, Estimate]:
    """IQM, median and mean with their CIs, and the catastrophic rate, of per-episode errors."""
    return {**{name: bootstrap_ci(x, name, seed) for name in STATISTICS}, "catastrophic": catastrophic_rate(x)}


def _paired(a, b) -> tuple[np.ndarray, np.ndarray]:
    a, b = _as_1d("a", a), _as_1d("b", b)
    if a.shape != b.shape:
        raise ValueError(f"paired arrays: lengths {a.size} and {b.size} differ (one value per shared seed)")
    return a, b


def paired_difference(a, b, statistic: str = "iqm", seed: int | None = 0,
                      n_resamples: int = N_RESAMPLES) -> Estimate:
    """``statistic(a) - statistic(b)`` with a CI from resampling seeds (pairs kept together).

    Negative means ``a`` has the lower error. Significant when the CI excludes zero.
    """
    a, b = _paired(a, b)
    fn = STATISTICS[statistic]
    value = float(fn(a) - fn(b))
    if a.size < 2 or np.ptp(a - b) == 0:
        return Estimate(value, value, value, a.size)
    res = stats.bootstrap((a, b), lambda u, v, axis=-1: fn(u, axis=axis) - fn(v, axis=axis), paired=True,
                          n_resamples=n_resamples, confidence_level=CONFIDENCE, method="percentile",
                          vectorized=True, axis=-1, random_state=_rng(seed))
    low, high = res.confidence_interval
    return Estimate(value, float(low), float(high), a.size)


def paired_relative_improvement(a, b, statistic: str = "iqm", seed: int | None = 0,
                                n_resamples: int = N_RESAMPLES) -> Estimate:
    """``1 - statistic(a) / statistic(b)``: how much lower ``a``'s error is, as a fraction of
    ``b``'s (> 0: ``a`` better), with a CI from resampling seeds (pairs kept together): the
    uncertainty of the denominator is in it, unlike a difference's CI divided by a point value."""
    a, b = _paired(a, b)
    fn = STATISTICS[statistic]
    value = float(1.0 - fn(a) / fn(b))
    if a.size < 2 or np.ptp(a - b) == 0:
        return Estimate(value, value, value, a.size)
    res = stats.bootstrap((a, b), lambda u, v, axis=-1: 1.0 - fn(u, axis=axis) / fn(v, axis=axis), paired=True,
                          n_resamples=n_resamples, confidence_level=CONFIDENCE, method="percentile",
                          vectorized=True, axis=-1, random_state=_rng(seed))
    low, high = res.confidence_interval
    return Estimate(value, float(low), float(high), a.size)


def _poi(u, v, axis=-1):
    # P(a < b) + 0.5 P(a == b) over all pairs (the Mann-Whitney U / (n m) of rliable).
    u, v = np.moveaxis(u, axis, -1), np.moveaxis(v, axis, -1)
    less = (u[..., :, None] < v[..., None, :]).mean(axis=(-1, -2))
    ties = (u[..., :, None] == v[..., None, :]).mean(axis=(-1, -2))
    return less + 0.5 * ties


def probability_of_improvement(a, b, seed: int | None = 0, n_resamples: int = N_RESAMPLES) -> Estimate:
    """Probability that an episode of ``a`` has a lower error than one of ``b`` (0.5 = no
    difference), with a paired bootstrap CI."""
    a, b = _paired(a, b)
    value = float(_poi(a, b))
    if a.size < 2:
        return Estimate(value, value, value, a.size)
    res = stats.bootstrap((a, b), _poi, paired=True, n_resamples=n_resamples, confidence_level=CONFIDENCE,
                          method="percentile", vectorized=False, random_state=_rng(seed))
    low, high = res.confidence_interval
    return Estimate(value, float(low), float(high), a.size)


def interpolate_curve(rates: np.ndarray, values: np.ndarray, at: float) -> float:
    """Piecewise-linear value of a sweep (points ``rates``, ``values``) at rate ``at``; NaN
    outside the sweep's range (no extrapolation)."""
    order = np.argsort(rates)
    r, v = np.asarray(rates)[order], np.asarray(values)[order]
    if not r[0] <= at <= r[-1]:
        return float("nan")
    return float(np.interp(at, r, v))


def matched_budget(sweep_rates, sweep_errors, target_rates, statistic: str = "iqm", seed: int | None = 0,
                   n_resamples: int = 1000) -> Estimate:
    """A sweep's error interpolated at a policy's budget, with a CI from resampling seeds.

    Args:
        sweep_rates, sweep_errors: (n_points, n_seeds) per-episode budget (e.g. calibrations per
            minute) and error of each sweep point (e.g. each fixed interval) on the same seeds.
        target_rates: (n_seeds,) the compared policy's per-episode budget on those seeds.

    Each resample draws seeds (``scipy.stats.bootstrap`` over seed indices), recomputes every
    sweep point's mean budget and ``statistic`` of error and the target's mean budget, and
    interpolates (clamped at the sweep's ends inside resamples). The point value is NaN when
    the target's budget lies outside the sweep: no extrapolation.
    """
    rates = np.asarray(sweep_rates, dtype=float)
    errors = np.asarray(sweep_errors, dtype=float)
    target = _as_1d("target_rates", target_rates)
    if rates.ndim != 2 or rates.shape != errors.shape or rates.shape[1] != target.size:
        raise ValueError(f"sweep_rates {rates.shape}, sweep_errors {errors.shape}, target_rates {target.shape}: "
                         "expected (n_points, n_seeds) twice and (n_seeds,)")
    fn = STATISTICS[statistic]

    def at(idx, clamp=True):
        idx = np.asarray(idx, dtype=int)
        r, v, t = rates[:, idx].mean(axis=1), fn(errors[:, idx], axis=1), target[idx].mean()
        if clamp:
            order = np.argsort(r)
            return float(np.interp(t, r[order], v[order]))
        return interpolate_curve(r, v, t)

    n = target.size
    value = at(np.arange(n), clamp=False)
    if n < 2 or not np.isfinite(value):
        return Estimate(value, float("nan"), float("nan"), n)
    res = stats.bootstrap((np.arange(n),), at, n_resamples=n_resamples, confidence_level=CONFIDENCE,
                          method="percentile", vectorized=False, random_state=_rng(seed))
    low, high = res.confidence_interval
    return Estimate(value, float(low), float(high), n)


def gap_closed_fraction(best_heuristic: float, learned: float, reference: float) -> float:
    """(best heuristic - learned) / (best heuristic - reference): 1 = as good as the reference,
    0 = no better than the heuristic, < 0 = worse; NaN when the reference is no better."""
    gap = best_heuristic - reference
    return float((best_heuristic - learned) / gap) if gap > 0 else float("nan")
