import numpy as np
import pytest

from uwb_env.config import OdometryConfig
from uwb_env.sim.odometry import OdometryModel


def test_uniform_model_variance_is_e2_over_3_per_axis(rng):
    e = 0.1
    model = OdometryModel(OdometryConfig(model="uniform", uniform_error_m=e))
    model.reset(5, rng)
    delta = np.zeros((5, 2))
    errors = np.array([model.estimated_displacement(delta, np.zeros(5), 0.2, rng) for _ in range(20000)])
    var = errors.reshape(-1, 2).var(axis=0)
    np.testing.assert_allclose(var, e**2 / 3, rtol=0.03)
    assert np.abs(errors).max() <= e


def test_distance_model_error_grows_with_distance(rng):
    cfg = OdometryConfig(model="distance", scale_error_std=0.0, yaw_noise_std_rad_per_sqrt_m=0.0,
                         yaw_noise_std_rad_per_rad=0.0, slip_rate_per_s=0.0,
                         noise_std_m_per_sqrt_m=0.05)
    model = OdometryModel(cfg)
    n = 4000
    model.reset(n, rng)
    for step_m in (0.1, 0.4):
        delta = np.tile([step_m, 0.0], (n, 1))
        err = model.estimated_displacement(delta, np.zeros(n), 0.2, rng) - delta
        # white noise std = 0.05 * sqrt(distance) per axis
        np.testing.assert_allclose(err.std(axis=0), 0.05 * np.sqrt(step_m), rtol=0.06)
    # no motion, no error (drift is driven by motion in this model)
    assert np.all(model.estimated_displacement(np.zeros((n, 2)), np.zeros(n), 0.2, rng) == 0)


def test_distance_model_scale_error_is_per_robot(rng):
    cfg = OdometryConfig(model="distance", scale_error_std=0.05, noise_std_m_per_sqrt_m=0.0,
                         yaw_noise_std_rad_per_sqrt_m=0.0, yaw_noise_std_rad_per_rad=0.0,
                         slip_rate_per_s=0.0)
    model = OdometryModel(cfg)
    model.reset(3000, rng)
    delta = np.tile([1.0, 0.0], (3000, 1))
    out = model.estimated_displacement(delta, np.zeros(3000), 0.2, rng)
    again = model.estimated_displacement(delta, np.zeros(3000), 0.2, rng)
    np.testing.assert_allclose(out, again)  # systematic, not white
    assert out[:, 0].std() == pytest.approx(0.05, rel=0.08)


def test_slip_phases_make_drift_vary_over_time(rng):
    cfg = OdometryConfig(model="distance", slip_rate_per_s=0.1, slip_duration_s=2.0,
                         slip_noise_multiplier=10.0, scale_error_std=0.0,
                         yaw_noise_std_rad_per_sqrt_m=0.0, yaw_noise_std_rad_per_rad=0.0)
    model = OdometryModel(cfg)
    model.reset(1, rng)
    delta = np.array([[0.1, 0.0]])
    errs = np.array([np.abs(model.estimated_displacement(delta, np.zeros(1), 0.2, rng) - delta).sum()
                     for _ in range(5000)])
    base = cfg.noise_std_m_per_sqrt_m * np.sqrt(0.1)
    assert (errs > 5 * base).mean() > 0.05  # ~17 % of steps slip (rate 0.1/s, 2 s each)
    assert np.median(errs) < 3 * base  # most are not


def _drift_after_reset(cfg: OdometryConfig, rng, n=6000, before_steps=150, after_steps=100, dt=0.2):
    """Robots drive curvy paths; 'calibrate' after ``before_steps`` (the estimate is reset to the
    truth, the heading error is not: a position fix does not observe it) and return the measured
    drift variance after ``after_steps`` more, with the model's prediction from what the robots
    measured (distance, heading variance then and now)."""
    model = OdometryModel(cfg)
    model.reset(n, rng)
    heading = rng.uniform(-np.pi, np.pi, n)

    def drive(steps):
        nonlocal heading
        err, dist = np.zeros((n, 2)), np.zeros(n)
        for _ in range(steps):
            turn = 0.3 * rng.standard_normal(n)
            heading = heading + turn
            step_m = 0.5 * dt
            delta = step_m * np.column_stack([np.cos(heading), np.sin(heading)])
            err += model.estimated_displacement(delta, np.abs(turn), dt, rng) - delta
            dist += step_m
        return err, dist

    drive(before_steps)
    model.restart_drift()
    err, _ = drive(after_steps)
    return (err * err).sum(1).mean(), model.expected_drift_var_m2(2).mean()


@pytest.mark.parametrize("slips", [False, True])
def test_predicted_drift_variance_matches_the_simulated_drift(rng, slips):
    # The predicted variance feeds the calibration priors, the relocation's weights of the other
    # anchors and the schedulers' features: it must say how far the estimates really drift,
    # including the heading error carried across calibrations and the slips in expectation.
    cfg = OdometryConfig(model="distance", yaw_noise_std_rad_per_sqrt_m=0.03, yaw_noise_std_rad_per_rad=0.03,
                         slip_rate_per_s=0.05 if slips else 0.0, slip_duration_s=4.0, slip_noise_multiplier=4.0)
    measured, predicted = _drift_after_reset(cfg, rng)
    assert predicted == pytest.approx(measured, rel=0.12)


@pytest.mark.parametrize("model", ["distance", "uniform"])
def test_drift_since_a_snapshot_stays_predicted_after_the_restart(rng, model):
    # A calibration solves for the positions at its round's midpoint; the estimate is that plus
    # the odometry since. Restarting from a snapshot taken at the midpoint, the prediction must
    # carry the drift since then (zeroing it made a fresh estimate look exact), on curvy paths,
    # and go on from there.
    cfg = OdometryConfig(model=model, scale_error_std=0.05, yaw_noise_std_rad_per_sqrt_m=0.03,
                         yaw_noise_std_rad_per_rad=0.03, slip_rate_per_s=0.0)
    n, dt = 8000, 0.2
    odo = OdometryModel(cfg)
    odo.reset(n, rng)
    heading = rng.uniform(-np.pi, np.pi, n)
    speed = rng.uniform(0.2, 1.2, n)

    def drive(steps):
        nonlocal heading
        err = np.zeros((n, 2))
        for _ in range(steps):
            turn = 0.4 * rng.standard_normal(n)
            heading = heading + turn
            delta = (speed * dt)[:, None] * np.column_stack([np.cos(heading), np.sin(heading)])
            err += odo.estimated_displacement(delta, np.abs(turn), dt, rng) - delta
        return err

    drive(100)  # a heading error to carry
    odo.restart_drift()
    drive(20)
    drive(8)  # first half of a 16-step round
    mid = odo.snapshot()
    second_half = drive(8)
    odo.restart_drift(since=mid)
    predicted = odo.expected_drift_var_m2(2).mean()
    measured = (second_half**2).sum(1).mean()
    assert measured > 0.0
    assert predicted == pytest.approx(measured, rel=0.1)
    later = second_half + drive(30)
    assert odo.expected_drift_var_m2(2).mean() == pytest.approx((later**2).sum(1).mean(), rel=0.1)


def test_restart_since_a_snapshot_of_some_robots_leaves_the_others(rng):
    cfg = OdometryConfig(model="distance")
    odo = OdometryModel(cfg)
    odo.reset(4, rng)
    for _ in range(10):
        odo.estimated_displacement(np.full((4, 2), 0.1), np.zeros(4), 0.2, rng)
    before = odo.expected_drift_var_m2(2)
    mask = np.array([False, True, False, True])
    snap = odo.snapshot(mask)
    for _ in range(5):
        odo.estimated_displacement(np.full((4, 2), 0.1), np.zeros(4), 0.2, rng)
    grown = odo.expected_drift_var_m2(2)
    odo.restart_drift(mask, since=snap)
    after = odo.expected_drift_var_m2(2)
    np.testing.assert_array_equal(after[~mask], grown[~mask])
    assert np.all(after[mask] > 0) and np.all(after[mask] < before[mask])


@pytest.mark.parametrize("model", ["distance", "uniform"])
def test_drift_between_two_snapshots_is_the_prediction_restarted_at_the_first(rng, model):
    # A round's carry variance is the drift between a pair's time and the midpoint: the same
    # prediction as a restart at the earlier snapshot, without touching the robots' state.
    cfg = OdometryConfig(model=model, scale_error_std=0.05, yaw_noise_std_rad_per_sqrt_m=0.03,
                         yaw_noise_std_rad_per_rad=0.03, slip_rate_per_s=0.05)
    odo = OdometryModel(cfg)
    odo.reset(6, rng)

    def drive(steps):
        for _ in range(steps):
            turn = 0.4 * rng.standard_normal(6)
            odo.estimated_displacement(rng.normal(0, 0.2, (6, 2)), np.abs(turn), 0.2, rng)

    drive(40)
    odo.restart_drift()
    drive(10)
    earlier = odo.snapshot()
    drive(7)
    later = odo.snapshot()
    between = odo.drift_var_between(earlier, later, dim=2)
    assert np.all(between > 0)
    assert odo.drift_var_between(later, later, dim=2) == pytest.approx(np.zeros(6), abs=1e-15)
    odo.restart_drift(since=earlier)
    np.testing.assert_allclose(between, odo.expected_drift_var_m2(2), rtol=1e-12)
    # snapshots on either side of a restart are not comparable: an error, not a wrong variance
    drive(3)
    with pytest.raises(ValueError, match="restart"):
        odo.drift_var_between(earlier, odo.snapshot())
