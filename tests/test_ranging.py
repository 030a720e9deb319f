import numpy as np
import pytest

from uwb_env.config import RangingConfig
from uwb_env.sim.ranging import RangeModel, fit_range_data, load_range_data


def test_fit_matches_the_shipped_data():
    true_m, measured_m = load_range_data()
    assert len(true_m) == 39
    fit = fit_range_data(true_m, measured_m)
    # The paper's Fig. 3 fit: ~1.0086 d + 0.361 m, residual ~5.9 cm.
    assert fit.slope == pytest.approx(1.0086, abs=2e-3)
    assert fit.offset_m == pytest.approx(0.361, abs=5e-3)
    assert fit.residual_std_m == pytest.approx(0.059, abs=3e-3)


def test_simulated_ranges_reproduce_the_fit(rng):
    model = RangeModel(RangingConfig(nlos_probability=0.0, dropout_probability=0.0))
    true_m, _ = load_range_data()
    truth = np.tile(true_m, 2000)  # the data's own distances, many times
    sim = model.measure(truth, rng)
    refit = fit_range_data(truth, sim)
    assert refit.slope == pytest.approx(model.slope, abs=1.5e-3)
    assert refit.offset_m == pytest.approx(model.offset_m, abs=5e-3)
    assert refit.residual_std_m == pytest.approx(model.noise_std_m, rel=0.03)


def test_correction_removes_the_bias(rng):
    model = RangeModel(RangingConfig(nlos_probability=0.0, dropout_probability=0.0))
    truth = np.full(20000, 7.0)
    corrected = model.correct(model.measure(truth, rng))
    assert abs(corrected.mean() - 7.0) < 3 * model.corrected_noise_std_m / np.sqrt(len(truth)) + 1e-3
    raw = model.measure(truth, rng)
    assert raw.mean() - 7.0 > 0.3  # the raw bias would not average out


def test_nlos_is_a_positive_bias_with_the_configured_rate(rng):
    cfg = RangingConfig(nlos_probability=0.2, nlos_bias_mean_m=0.5, dropout_probability=0.0)
    model = RangeModel(cfg)
    truth = np.full(50000, 5.0)
    resid = model.correct(model.measure(truth, rng)) - truth
    outliers = resid > 6 * model.corrected_noise_std_m
    # P(bias > 6 sigma) for Exp(0.5 m) is exp(-0.35/0.5) ~ 0.50, times p = 0.2 -> ~0.1
    assert 0.07 < outliers.mean() < 0.13
    # the correction removes the excess's mean too: the corrected ranges are unbiased
    assert resid.mean() == pytest.approx(0.0, abs=0.005)
    raw_resid = model.undo_linear_bias(model.measure(truth, rng)) - truth
    assert raw_resid.mean() == pytest.approx(0.2 * 0.5 / model.slope, abs=0.01)


def test_corrected_range_std_includes_the_nlos_excess(rng):
    # A calibration pair's mean averages K ranges of the mixture: its variance is the mixture's
    # second moment over K, not the Gaussian part's (that made later calibrations ~3x
    # overconfident under the default radio).
    clean = RangeModel(RangingConfig(nlos_probability=0.0))
    assert clean.corrected_range_std_m == pytest.approx(clean.corrected_noise_std_m)
    model = RangeModel(RangingConfig(nlos_probability=0.1, nlos_bias_mean_m=0.4, dropout_probability=0.0))
    corrected = model.correct(model.measure(np.full(200_000, 6.0), rng))
    assert corrected.std() == pytest.approx(model.corrected_range_std_m, rel=0.02)
    assert model.corrected_range_std_m > 2 * model.corrected_noise_std_m


def test_dropout_and_max_range(rng):
    model = RangeModel(RangingConfig(dropout_probability=0.1, max_range_m=10.0))
    out = model.measure(np.array([5.0] * 20000 + [11.0] * 10), rng)
    assert np.isnan(out[-10:]).all()
    assert np.isnan(out[:-10]).mean() == pytest.approx(0.1, abs=0.01)


def test_missing_data_file_is_a_clear_error():
    with pytest.raises(FileNotFoundError, match="data_file"):
        RangeModel(RangingConfig(data_file="no_such_file.csv"))
