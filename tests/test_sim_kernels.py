# ruff: noqa: E501  (recorded values, one list per line)
"""The compiled motion, odometry and ranging loops reproduce the numpy implementation they
replaced (25a3f64): the values below were recorded from it for fixed seeds. Same seed, same
trajectory, so every committed episode result stays valid; a changed formula or draw order
shows up here (see RTOL for the last-bit differences between CPUs)."""

import numpy as np
import pytest

from uwb_env.config import MotionConfig, OdometryConfig, RangingConfig
from uwb_env.sim.motion import MotionModel
from uwb_env.sim.odometry import OdometryModel
from uwb_env.sim.ranging import RangeModel

# The same operations in the same order (and roundings) as numpy, to the last bit or two: the
# kernels call libm's exp where numpy, on CPUs with AVX-512 (X86_V4), dispatches float64 exp to
# its own SIMD routine, which differs from libm in the last bit on ~5 % of inputs (an AMD EPYC
# VM: recorded trajectories off by <= 7e-15 m). A changed formula, draw order or missing
# rounding step shows up many orders of magnitude above this tolerance.
RTOL = 1e-12

RECORDED_MOTION = {
    'heading': (
        [6.128268814291227, 13.502114300150959, 13.879850673749209, 16.112660792387235, 9.54923870155634, 9.704823022464442, 10.109339576760439],
        [19.255011262656524, 17.986775725655125, 23.642508849331897, 19.969919838785547, 19.356518668051077, 13.520318233833205, 7.773955365227179],
        [-11.631868638969443, 6.975052288495718, -3.385040906712355, -11.368013225202589, 5.9815924745205695, 10.008756283096451, 4.704385825000767]),
    'stop_and_go': (
        [10.17309973694742, 7.908053882361179, 18.04191383732601, 13.884558893094137, 13.09074812036926, 4.495214894050587, 7.148374767508108],
        [19.420572544942292, 18.426713493829553, 20.285806635984137, 21.627486255680992, 7.392100768911315, 7.731394380878195, 8.293054502228518],
        [-17.667890848382108, 12.304603160622024, -3.7882772399062894, -6.125585903103644, -1.421902257236015, 11.377258625536088, 5.784800255304349]),
    'patrol': (
        [11.760785261084848, 15.819912127871179, 5.409274110369038, 0.07712166261572155, 7.38471424889681, 11.006192418162783, 8.281693819431576],
        [24.45307288986725, 28.875523595502372, 25.838988365332973, 29.294127729656118, 17.54713194913341, 8.8756189467844, 7.408458699633439],
        [0.8079170669859899, 0.6778537473411061, -0.32111316344463603, 0.2966516387584761, 5.774376986349898, 4.7382542636811475, 6.056378514102262]),
}
RECORDED_ODOMETRY = (
    [0.666445173653439, 2.002127314316679, 1.6033638403840886, 1.651002103347798, 1.9246119982285392, -1.341568554057888, 0.7768617730522892, 0.36236977536732917, -1.4292039372824341, 0.5503496083022185],
    [2.0455344103871065, 3.0062802624670577, 2.507626558254857, 1.8245909068103703, 2.1472771359792455])
RECORDED_RANGES = [1.4906472868949014, 3.8774463837900814, np.nan, 9.313478446489713, 11.979427425207545, 14.652600382421696, 17.696718355184938, 19.969889694980463, 22.591498869342466, 26.349678988144284, 28.336790938250335, 30.599253009480364]


@pytest.mark.parametrize("model", sorted(RECORDED_MOTION))
def test_motion_kernel_reproduces_recorded_trajectory(model):
    # anchors on `model`, tags inside their hull; 300 steps cross walls, waypoints and pauses
    m = MotionModel([(MotionConfig(model=model), 4), (MotionConfig(model="inside_hull"), 3)], 20.0)
    rng = np.random.default_rng(7)
    m.reset(rng.uniform(0, 20, (7, 2)), rng)
    turn, step = np.zeros(7), np.zeros((7, 2))
    for _ in range(300):
        d, t = m.step(0.2, rng)
        turn += t
        step += d
    x, total_turn, total_dy = RECORDED_MOTION[model]
    np.testing.assert_allclose(m.positions[:, 0], x, rtol=RTOL)
    np.testing.assert_allclose(turn, total_turn, rtol=RTOL)
    np.testing.assert_allclose(step[:, 1], total_dy, rtol=RTOL)


def test_odometry_kernel_reproduces_recorded_drift():
    o = OdometryModel(OdometryConfig(slip_rate_per_s=1.0))  # slips exercised
    rng = np.random.default_rng(11)
    o.reset(5, rng)
    acc = np.zeros((5, 2))
    for _ in range(200):
        acc += o.estimated_displacement(rng.normal(size=(5, 2)) * 0.1, abs(rng.normal(size=5)) * 0.1, 0.2, rng)
    displacement, drift_var = RECORDED_ODOMETRY
    np.testing.assert_allclose(acc.ravel(), displacement, rtol=RTOL)
    np.testing.assert_allclose(o.expected_drift_var_m2(2), drift_var, rtol=RTOL)


def test_range_kernel_reproduces_recorded_draws():
    model = RangeModel(RangingConfig(nlos_probability=0.3, dropout_probability=0.1))
    out = model.measure(np.linspace(1, 30, 12).reshape(3, 4), np.random.default_rng(3))
    assert out.shape == (3, 4)
    np.testing.assert_allclose(out.ravel(), RECORDED_RANGES, rtol=RTOL)  # NaN where recorded lost


def test_odometry_3d_keeps_vertical_motion_exact():
    o = OdometryModel(OdometryConfig())
    rng = np.random.default_rng(0)
    o.reset(3, rng)
    delta = rng.normal(size=(3, 3))
    out = o.estimated_displacement(delta, np.zeros(3), 0.2, rng)
    np.testing.assert_array_equal(out[:, 2], delta[:, 2])
    assert np.isfinite(out).all()


def test_drift_variance_of_every_robot_equals_that_of_each_subset():
    # the compiled all-robots path and the numpy path for index subsets say the same
    o = OdometryModel(OdometryConfig(slip_rate_per_s=0.5))
    rng = np.random.default_rng(1)
    o.reset(20, rng)
    for t in range(120):
        o.estimated_displacement(rng.normal(size=(20, 2)) * 0.2, abs(rng.normal(size=20)) * 0.1, 0.2, rng)
        if t % 40 == 0:
            o.restart_drift(np.arange(5), since=o.snapshot(np.arange(5)))
    everyone = o.expected_drift_var_m2(2)
    assert (everyone > 0).all()
    np.testing.assert_array_equal(everyone, o.expected_drift_var_m2(2, np.arange(20)))
    np.testing.assert_array_equal(everyone[3:7], o.expected_drift_var_m2(2, np.arange(3, 7)))


# Robot 25's positions at steps 115-119 of the scene below, recorded from the numpy code: with
# zero-length pauses a robot that reaches its waypoint steps exactly the distance to it, so the
# distance must be numpy's |z| to the last bit (math.hypot differs here in the 16th digit).
RECORDED_ZERO_PAUSE = [4.465281843132985, 0.07686815034885125, 4.378734684076205, 0.06685583561782901, 4.29171183160692, 0.06658317554806069, 4.205556145557497, 0.05895079929814973, 4.116945328195512, 0.05174222320788706]


def test_motion_kernel_steps_numpys_waypoint_distance():
    m = MotionModel([(MotionConfig(model="patrol"), 4),
                     (MotionConfig(model="patrol", pause_min_s=0.0, pause_max_s=0.0), 40)], 20.0)
    rng = np.random.default_rng(42)
    m.reset(rng.uniform(0, 20, (44, 2)), rng)
    seen = []
    for t in range(120):
        m.step(0.2, rng)
        if t >= 115:
            seen.append(m.positions[25].copy())
    np.testing.assert_allclose(np.ravel(seen), RECORDED_ZERO_PAUSE, rtol=RTOL)


def _numpy_recentred(since, now):
    """The numpy re-centring the compiled ``_recentre`` replaced (``odometry._recentred`` at 4385f0e)."""
    p_s = since["_net"]
    d_a = now["_sum_a"] - since["_sum_a"]
    d_b = now["_sum_b"] - since["_sum_b"]
    d_c = now["_sum_c"] - since["_sum_c"]
    cross = p_s.real * d_b.real + p_s.imag * d_b.imag
    return {"_h0": since["heading_var_rad2"], "_dist": now["_dist"] - since["_dist"], "_net": now["_net"] - p_s,
            "_sum_a": d_a, "_sum_b": d_b - d_a * p_s, "_sum_c": d_c - 2.0 * cross + d_a * (p_s.real**2 + p_s.imag**2)}


def _numpy_variance(odo, acc):
    cfg = odo.config
    p, b = acc["_net"], acc["_sum_b"]
    p2 = p.real * p.real + p.imag * p.imag
    cross = p.real * b.real + p.imag * b.imag
    white = 2 * cfg.noise_std_m_per_sqrt_m**2 * odo.expected_slip_gain2 * acc["_dist"]
    heading = (cfg.scale_error_std**2 + acc["_h0"] + acc["_sum_a"]) * p2 - 2 * cross + acc["_sum_c"]
    return white + np.maximum(heading, 0.0)


def test_compiled_drift_between_snapshots_is_the_numpy_formula_to_the_last_bit():
    # A round's carry variance and the re-centring after a calibration: the compiled loops give
    # the numbers of the numpy code they replaced (same operations, same order), so episodes
    # with calibrations keep their trajectories bit for bit.
    rng = np.random.default_rng(3)
    o = OdometryModel(OdometryConfig(slip_rate_per_s=0.5, scale_error_std=0.03))
    o.reset(9, rng)
    snaps = []
    for _ in range(12):
        o.estimated_displacement(rng.normal(0, 0.2, (9, 2)), np.abs(rng.normal(0, 0.3, 9)), 0.2, rng)
        snaps.append(o.snapshot())
    k_mid = 5
    steps = np.arange(len(snaps))
    series = o.drift_var_series(snaps, np.minimum(steps, k_mid), np.maximum(steps, k_mid))
    for t, s in enumerate(snaps):
        early, late = (s, snaps[k_mid]) if t <= k_mid else (snaps[k_mid], s)
        np.testing.assert_array_equal(series[t], _numpy_variance(o, _numpy_recentred(early, late)))
    assert np.all(series[steps != k_mid] > 0) and np.all(series[k_mid] == 0)
    # the re-centring a calibration applies (restart_drift), on a subset of the robots
    robots = np.array([1, 4, 8])
    expected = _numpy_recentred({k: v[robots] for k, v in snaps[3].items()}, o.snapshot(robots))
    o.restart_drift(robots, since={k: v[robots] for k, v in snaps[3].items()})
    for name, value in expected.items():
        np.testing.assert_array_equal(getattr(o, name)[robots], value, err_msg=name)


def test_compiled_path_interpolation_is_numpys():
    from uwb_env.sim._round_path_kernel import interpolate

    rng = np.random.default_rng(4)
    times = np.cumsum(rng.uniform(0.05, 0.3, 7))
    stack = rng.normal(size=(7, 10))
    t = np.concatenate([rng.uniform(times[0] - 0.5, times[-1] + 0.5, 40), times])  # outside, inside, on the boundaries
    s = np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(times) - 2)
    w = ((t - times[s]) / np.maximum(times[s + 1] - times[s], 1e-12))[:, None]
    np.testing.assert_array_equal(interpolate(times, stack, t), (1.0 - w) * stack[s] + w * stack[s + 1])


def test_batched_distance_and_frame_kernels_are_numpys_numbers():
    # the batched env's compiled tag distances and odometry-in-frame update replaced numpy
    # calls; a copy's trajectory must not move by a bit
    from uwb_env.sim._odometry_kernel import add_rotated
    from uwb_env.sim.ranging import planar_distances

    rng = np.random.default_rng(5)
    tags, anchors = rng.uniform(-30, 30, (50, 3, 2)), rng.uniform(-30, 30, (50, 4, 2))
    np.testing.assert_array_equal(planar_distances(tags, anchors),
                                  np.linalg.norm(tags[:, :, None, :] - anchors[:, None, :, :], axis=-1))
    angle = rng.uniform(-np.pi, np.pi, 50)
    rot = np.stack([[[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]] for a in angle])
    odo = rng.normal(0, 0.1, (50, 4, 2)) * rng.choice([1e-3, 1.0, 1e3], (50, 4, 2))
    est = rng.uniform(-30, 30, (50, 4, 2))
    want = est + np.einsum("bnj,bij->bni", odo, rot)
    add_rotated(est, odo, rot)
    np.testing.assert_array_equal(est, want)


@pytest.mark.parametrize("dim", [2, 3])
def test_round_exchange_distances_are_the_numpy_expression(dim):
    from uwb_env.sim.calibration_round import _exchange_distances

    rng = np.random.default_rng(dim)
    a0 = rng.uniform(0, 30, (5, 6, dim))
    a1 = a0 + rng.normal(0, 0.3, a0.shape)
    initiator = rng.integers(0, 6, 40)
    responder = (initiator + rng.integers(1, 6, 40)) % 6
    t = np.sort(rng.uniform(1.0, 1.2, 40))
    alpha = ((t - 1.0) / max(1.2 - 1.0, 1e-12))[:, None]  # the span as the round computes it
    pi = a0[..., initiator, :] + alpha * (a1[..., initiator, :] - a0[..., initiator, :])
    pj = a0[..., responder, :] + alpha * (a1[..., responder, :] - a0[..., responder, :])
    np.testing.assert_array_equal(_exchange_distances(t, 1.0, 1.2, a0, a1, initiator, responder),
                                  np.linalg.norm(pi - pj, axis=-1))


def test_drift_variance_takes_any_numpy_index():
    rng = np.random.default_rng(8)
    o = OdometryModel(OdometryConfig())
    o.reset(6, rng)
    for _ in range(5):
        o.estimated_displacement(rng.normal(0, 0.2, (6, 2)), np.abs(rng.normal(0, 0.2, 6)), 0.2, rng)
    everyone = o.expected_drift_var_m2(2)
    index = np.array([[0, 1], [4, 5]])
    np.testing.assert_array_equal(o.expected_drift_var_m2(2, index), everyone[index])
    single = o.expected_drift_var_m2(2, 3)
    assert np.ndim(single) == 0 and single == everyone[3]
    assert o.expected_drift_var_m2(2, np.zeros(6, dtype=bool)).shape == (0,)


def test_compiled_slip_step_is_the_numpy_bookkeeping():
    from uwb_env.sim._odometry_kernel import slip_step

    rng = np.random.default_rng(9)
    n, q, dt, duration, mult = 50, 1.5, 0.2, 1.0, 3.0
    left_np, left_k, any_np = np.zeros(n), np.zeros(n), False
    for _ in range(200):
        noise = rng.standard_normal(4 * n)
        start = noise[3 * n:] > q
        gain_np = None
        if any_np or start.any():  # the numpy code the kernel replaced
            slipping = left_np > 0.0
            left_np = np.where(start & ~slipping, duration, np.maximum(left_np - dt, 0.0))
            any_np = bool((left_np > 0.0).any())
            gain_np = np.where(slipping, mult, 1.0)
        gain_k = np.empty(n)
        touched, any_k = slip_step(left_k, noise, q, bool((left_k > 0).any()), dt, duration, mult, gain_k)
        assert touched == (gain_np is not None)
        np.testing.assert_array_equal(left_k, left_np)
        if touched:
            assert any_k == any_np
            np.testing.assert_array_equal(gain_k, gain_np)
