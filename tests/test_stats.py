"""The protocol's statistics: CIs cover what they should and reject what they should not."""

import numpy as np
import pytest

from uwb_env.evaluation.stats import (
    bootstrap_ci,
    catastrophic_rate,
    gap_closed_fraction,
    iqm,
    matched_budget,
    paired_difference,
    probability_of_improvement,
    summarize_errors,
)


def test_iqm_is_the_mean_of_the_middle_half():
    x = np.array([0.0, 1, 2, 3, 4, 5, 6, 1000])  # the outlier is trimmed away
    assert iqm(x) == pytest.approx(np.mean([2, 3, 4, 5]))


def test_ci_covers_the_true_value_and_rejects_a_biased_one():
    rng = np.random.default_rng(1)
    # Lognormal episode errors with a few catastrophic ones (as in the env): the median is known.
    true_median = 0.3
    x = true_median * np.exp(0.5 * rng.standard_normal(200))
    x[:6] += 3.0
    est = bootstrap_ci(x, "median")
    assert est.covers(true_median)
    biased = bootstrap_ci(x * 1.4, "median")  # a 40 % biased estimator of the same quantity
    assert not biased.covers(true_median)


def test_ci_coverage_rate_is_near_nominal():
    rng = np.random.default_rng(2)
    hits = sum(bootstrap_ci(rng.normal(1.0, 0.2, 40), "mean", seed=i, n_resamples=500).covers(1.0)
               for i in range(60))
    assert 0.85 * 60 <= hits <= 60


def test_catastrophic_rate_wilson_interval():
    x = np.r_[np.full(95, 0.2), np.full(5, 2.0)]
    est = catastrophic_rate(x)
    assert est.value == pytest.approx(0.05)
    assert est.ci_low < 0.05 < est.ci_high and est.ci_low > 0.01 and est.ci_high < 0.12
    assert catastrophic_rate(np.full(50, 0.2)).ci_high > 0  # zero failures still bound the rate


def test_paired_difference_sees_a_small_shift_hidden_by_seed_variance():
    rng = np.random.default_rng(3)
    seed_effect = rng.lognormal(-1.2, 0.8, 100)  # seeds differ far more than the policies do
    a = seed_effect
    b = seed_effect + 0.02 + 0.005 * rng.standard_normal(100)
    d = paired_difference(a, b, "mean")
    assert d.value == pytest.approx(-0.02, abs=0.003)
    assert d.excludes_zero() and d.ci_high < 0
    # Same data, no real difference: the CI contains zero.
    assert not paired_difference(a, a + 0.005 * rng.standard_normal(100), "mean").excludes_zero()
    with pytest.raises(ValueError, match="lengths"):
        paired_difference(a, b[:-1])


def test_probability_of_improvement():
    a, b = np.arange(10.0), np.arange(10.0) + 100
    assert probability_of_improvement(a, b).value == 1.0
    assert probability_of_improvement(a, a).value == pytest.approx(0.5)


def test_matched_budget_interpolates_with_a_ci():
    rng = np.random.default_rng(4)
    n = 60
    k_rates = np.array([3.0, 6.0, 12.0, 24.0])  # a fixed-interval sweep: error = 1 / rate
    rates = k_rates[:, None] + 0.2 * rng.standard_normal((4, n))
    errors = 1.0 / k_rates[:, None] * np.exp(0.1 * rng.standard_normal((4, n)))
    target = 9.0 + 0.3 * rng.standard_normal(n)
    est = matched_budget(rates, errors, target, "mean")
    expected = np.interp(9.0, k_rates, 1 / k_rates)  # the piecewise-linear curve at 9/min
    assert est.covers(expected) and est.ci_high - est.ci_low < 0.05
    # Outside the sweep there is no extrapolation.
    assert np.isnan(matched_budget(rates, errors, target + 100).value)


def test_summary_and_gap():
    s = summarize_errors(np.r_[np.full(20, 0.2), 3.0])
    assert set(s) == {"iqm", "median", "mean", "catastrophic"}
    assert s["iqm"].value == pytest.approx(0.2) and s["mean"].value > 0.3
    assert gap_closed_fraction(0.3, 0.25, 0.2) == pytest.approx(0.5)
    with pytest.raises(ValueError, match="finite"):
        bootstrap_ci([np.nan, 1.0])


def test_paired_relative_improvement_includes_the_denominators_uncertainty():
    from uwb_env.evaluation.stats import iqm, paired_relative_improvement

    rng = np.random.default_rng(4)
    b = rng.lognormal(np.log(0.15), 0.4, 120)
    a = 0.8 * b  # 20 % lower on every seed
    exact = paired_relative_improvement(a, b)
    assert (exact.value, exact.ci_low, exact.ci_high) == pytest.approx((0.2, 0.2, 0.2))
    a = 0.8 * b + rng.normal(0, 0.02, b.size)
    rel = paired_relative_improvement(a, b)
    assert rel.ci_low < rel.value < rel.ci_high
    # the same percentile bootstrap by hand: seeds resampled with their pairs
    idx = rng.integers(0, b.size, (4000, b.size))
    ratios = 1 - iqm(a[idx], axis=1) / iqm(b[idx], axis=1)
    low, high = np.percentile(ratios, [2.5, 97.5])
    assert rel.ci_low == pytest.approx(low, abs=0.01) and rel.ci_high == pytest.approx(high, abs=0.01)
