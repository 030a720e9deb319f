"""RoundPath: a round's ranges carried to its midpoint along the estimated path, the estimates
at the midpoint, the drift accumulators there."""

import numpy as np
import pytest

from uwb_env.config import CalibrationConfig, OdometryConfig, RangingConfig
from uwb_env.measurements import RangeMatrix
from uwb_env.sim.calibration_round import CalibrationRound, RoundTiming
from uwb_env.sim.odometry import OdometryModel
from uwb_env.sim.ranging import RangeModel
from uwb_env.sim.round_path import RoundPath, pair_mean_times_s


def _turning(n, steps, dt, rng):
    """Anchors that drive and turn sharply mid-round (patrol waypoints, stop-and-go): a straight
    line between a round's ends misplaces them by metres at its midpoint."""
    start = rng.uniform(0, 20, (n, 2))
    v1, v2 = rng.normal(0, 1.0, (n, 2)), rng.normal(0, 1.0, (n, 2))
    out, x = [start], start
    for s in range(steps):
        x = x + (v1 if s < steps // 2 else v2) * dt
        out.append(x)
    return out


def test_noise_free_ranges_carried_along_a_turning_path_are_the_midpoint_distances():
    rng = np.random.default_rng(0)
    n, dt = 5, 0.2
    timing = RoundTiming.fit(CalibrationConfig())
    noiseless = RangeModel(RangingConfig(noise_std_m=1e-12, nlos_probability=0.0, dropout_probability=0.0,
                                         correct_bias=True))
    rnd = CalibrationRound(n, timing, 1, 0.0)  # one exchange per pair: its time is the pair's time
    steps = int(np.ceil(rnd.times_s[-1] / dt)) + 1
    track = _turning(n, steps, dt, rng)
    path = RoundPath(0.0, track[0])
    s = 0
    while not rnd.done:
        rnd.advance(s * dt, (s + 1) * dt, track[s], track[s + 1], noiseless, rng)
        s += 1
        path.record(s * dt, track[s])
    matrix = rnd.result()
    raw = noiseless.correct(matrix.mean_m)
    carried = path.carry(raw, pair_mean_times_s(n, rnd.times_s, rnd.initiator, rnd.responder))
    # the midpoint geometry, from the path itself (linear within each step, as the world moves)
    t_mid = 0.5 * s * dt
    k = int(t_mid // dt)
    w = t_mid / dt - k
    mid = (1 - w) * track[k] + w * track[k + 1]
    truth = np.linalg.norm(mid[:, None] - mid[None], axis=-1)
    off = ~np.eye(n, dtype=bool)
    bias = np.abs(raw - truth)[off].max()
    assert bias > 0.1  # the round mixes geometries tens of centimetres apart
    np.testing.assert_allclose(carried[off], truth[off], atol=1e-6)
    np.testing.assert_allclose(path.midpoint_estimates(), mid, atol=1e-12)
    # a straight line between the ends is not where the robots were at the midpoint
    assert np.abs(0.5 * (track[0] + track[s]) - mid).max() > 0.1


def test_midpoint_drift_is_the_snapshot_nearest_the_midpoint(rng):
    odo = OdometryModel(OdometryConfig(model="distance"))
    odo.reset(3, rng)
    path = RoundPath(0.0, np.zeros((3, 2)), odo.snapshot())
    for s in range(1, 7):
        odo.estimated_displacement(np.full((3, 2), 0.1), np.zeros(3), 0.2, rng)
        path.record(0.2 * s, np.zeros((3, 2)), odo.snapshot())
    assert path.midpoint_time_s == pytest.approx(0.6)
    assert path.midpoint_drift()["_steps"] == pytest.approx(np.full(3, 3.0))


def test_hardware_rounds_without_exchange_times_are_not_carried():
    path = RoundPath(0.0, np.zeros((3, 2)))
    path.record(1.0, np.ones((3, 2)))
    mean = np.arange(9.0).reshape(3, 3)
    assert path.carry(mean, None) is mean
    assert path.carry_var_m2(None, OdometryModel(OdometryConfig())) is None


@pytest.mark.parametrize(("model", "dim"), [("distance", 2), ("uniform", 2), ("distance", 3)])
def test_carry_variance_predicts_the_carried_ranges_error(rng, model, dim):
    # Carrying a pair's range to the midpoint swaps the true change of its distance for the
    # estimated one, so the odometry's drift between the pair's time and the midpoint enters the
    # range. Without its variance a later calibration in a moving team was ~2.5x overconfident
    # (bench_consistency). Noise-free ranges, many copies of a 5-anchor round with turning,
    # drifting robots: the carried ranges' errors must have the predicted variance (in 3D the
    # drift is planar and anchors at similar heights: spread over three axes it was 1.3x short).
    copies, n, dt = 600, 5, 0.2
    odo = OdometryModel(OdometryConfig(model=model, noise_std_m_per_sqrt_m=0.08, scale_error_std=0.05,
                                       yaw_noise_std_rad_per_sqrt_m=0.05, slip_rate_per_s=0.0,
                                       uniform_error_m=0.03))
    odo.reset(copies * n, rng)
    timing = RoundTiming.fit(CalibrationConfig())
    rnd = CalibrationRound(n, timing, 5, 0.0)
    truth = np.concatenate([rng.uniform(0, 20, (copies, n, 2)), rng.uniform(0, 0.3, (copies, n, dim - 2))], -1)
    est = truth.copy()
    heading = rng.uniform(-np.pi, np.pi, (copies, n))
    for _ in range(30):  # a heading error to carry into the round
        odo.estimated_displacement(np.zeros((copies * n, dim)), np.zeros(copies * n), dt, rng)
    path = RoundPath(0.0, est, odo.snapshot(), truth)
    ranges = np.full((copies, len(rnd.times_s)), np.nan)
    s = 0
    while s * dt < rnd.end_time_s:
        turn = 0.5 * rng.standard_normal((copies, n))
        heading = heading + turn
        delta = 1.0 * dt * np.stack([np.cos(heading), np.sin(heading)] + [0 * heading] * (dim - 2), axis=-1)
        odo_delta = odo.estimated_displacement(delta.reshape(-1, dim), np.abs(turn).ravel(), dt, rng)
        t0, t1 = s * dt, (s + 1) * dt
        take = (rnd.times_s > t0) & (rnd.times_s <= t1)
        alpha = ((rnd.times_s[take] - t0) / dt)[:, None]
        a, b = truth[:, rnd.initiator[take]], truth[:, rnd.responder[take]]
        da, db = delta[:, rnd.initiator[take]], delta[:, rnd.responder[take]]
        ranges[:, take] = np.linalg.norm(a + alpha * da - b - alpha * db, axis=-1)
        truth = truth + delta
        est = est + odo_delta.reshape(copies, n, dim)
        s += 1
        path.record(s * dt, est, odo.snapshot(), truth)
    times = pair_mean_times_s(n, rnd.times_s, rnd.initiator, rnd.responder)
    mean = np.stack([_pair_means(n, rnd, r) for r in ranges])  # noise-free: the true distances
    carried = path.carry(mean, times)
    var = path.carry_var_m2(times, odo)
    mid = path.midpoint_truth()
    true_mid = np.linalg.norm(mid[:, :, None] - mid[:, None], axis=-1)
    off = ~np.eye(n, dtype=bool)
    err = (carried - true_mid)[:, off]
    assert np.abs(err).max() > 0.01  # the carry does add error
    ratio = np.mean(err**2) / np.mean(var[:, off])
    assert 0.6 < ratio < 1.25, ratio
    # zero at the midpoint, and larger for pairs ranged further from it
    far = np.abs(times - path.midpoint_time_s)[off]
    v = var[:, off].mean(0)
    assert np.corrcoef(far, v)[0, 1] > 0.8


def _pair_means(n, rnd, ranges):
    return RangeMatrix.from_samples(n, rnd.initiator, rnd.responder, ranges).mean_m
