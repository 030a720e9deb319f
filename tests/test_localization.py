import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy import stats

from uwb_env.localization import (
    DisconnectedGraphError,
    GeometryError,
    InvalidRangeError,
    PairRangeModel,
    TagRangeModel,
    TooFewAnchorsError,
    aligned_errors,
    calibrate_anchors,
    crlb_anchors,
    crlb_tags,
    locate_tags,
    paper_frame,
    rigid_align,
)
from uwb_env.localization.multilateration import DEGENERATE, OK, TOO_FEW_RANGES
from uwb_env.measurements import RangeMatrix


def distances(x):
    return np.linalg.norm(x[:, None] - x[None], axis=-1)


def well_posed(x, dim):
    """Anchors spread out enough to fix the frame (no near-coincident / collinear sets)."""
    d = distances(x)[np.triu_indices(len(x), 1)]
    if d.min() < 0.5:
        return False
    sv = np.linalg.svd(x - x.mean(0), compute_uv=False)
    if sv[dim - 1] < 0.5:
        return False
    try:
        paper_frame(x)
    except GeometryError:
        return False
    rot, trans = paper_frame(x)
    in_frame = x @ rot.T + trans
    if dim == 3:  # the third frame anchor (farthest off the x axis) must be clear, not a tie
        off = np.sort(np.linalg.norm(in_frame[:, 1:], axis=1))
        if off[-1] - off[-2] < 0.3:
            return False
    # the frame's sign rules need a clear side (sum of y, and of z in 3D, away from zero)
    return abs(in_frame[:, 1].sum()) > 0.3 and (dim == 2 or abs(in_frame[:, 2].sum()) > 0.3)




@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.filter_too_much])
@given(dim=st.integers(2, 3), n=st.integers(4, 9), data=st.data())
def test_noise_free_first_calibration_is_exact(dim, n, data):
    x = data.draw(arrays(np.float64, (n, dim), elements=st.floats(-20, 20)))
    assume(well_posed(x, dim))
    res = calibrate_anchors(distances(x), dim=dim, range_std_m=0.05)
    rot, trans = paper_frame(x)
    np.testing.assert_allclose(res.positions, x @ rot.T + trans, atol=1e-6)
    assert res.positions[0] == pytest.approx(np.zeros(dim))
    assert abs(res.positions[1, 1:]).max() < 1e-9 and res.positions[1, 0] > 0
    if dim == 2:
        assert res.positions[2:, 1].sum() > 0  # "the rest in +y"


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.filter_too_much])
@given(dim=st.integers(2, 3), n=st.integers(4, 9), data=st.data())
def test_noise_free_later_calibration_recovers_shape_and_keeps_anchor0(dim, n, data):
    x = data.draw(arrays(np.float64, (n, dim), elements=st.floats(-20, 20)))
    assume(well_posed(x, dim))
    noise = data.draw(arrays(np.float64, (n, dim), elements=st.floats(-0.3, 0.3)))
    prior = x + noise
    res = calibrate_anchors(distances(x), dim=dim, prior=prior, range_std_m=0.05)
    assert aligned_errors(res.positions, x).max() < 1e-6
    np.testing.assert_allclose(res.positions[0], prior[0], atol=1e-9)  # gauge "anchor0"
    np.testing.assert_allclose(distances(res.positions), distances(x), atol=1e-6)


def test_later_calibration_takes_the_priors_chirality(rng):
    x = rng.uniform(0, 10, (5, 2))
    mirrored = x * np.array([1.0, -1.0])
    res = calibrate_anchors(distances(x), prior=mirrored + rng.normal(0, 0.05, x.shape), range_std_m=0.05)
    np.testing.assert_allclose(res.positions, mirrored, atol=0.2)


def test_prior_gauge_averages_all_priors(rng):
    x = rng.uniform(0, 10, (6, 2))
    prior = x + np.array([0.5, 0.0])  # all priors off by the same shift
    prior[0] += np.array([1.0, 1.0])  # anchor 0 off by more
    a0 = calibrate_anchors(distances(x), prior=prior, gauge="anchor0", range_std_m=0.05)
    pr = calibrate_anchors(distances(x), prior=prior, gauge="prior", range_std_m=0.05)
    err = lambda p: np.linalg.norm(p - x, axis=1).mean()  # noqa: E731
    assert err(pr.positions) < err(a0.positions)


@pytest.mark.parametrize("dim", [2, 3])
def test_analytic_jacobians_match_finite_differences(dim, rng):
    x = rng.uniform(-5, 5, (6, dim))
    model = PairRangeModel(np.column_stack(np.triu_indices(6, 1)), 6)
    np.testing.assert_allclose(model.jacobian(x), model.jacobian_fd(x), atol=1e-7)
    tags = rng.uniform(-5, 5, (4, dim))
    tag_model = TagRangeModel(x)
    np.testing.assert_allclose(tag_model.jacobian(tags), tag_model.jacobian_fd(tags), atol=1e-7)


def _round(x, rng, sigma, k):
    """Per-ordered-pair mean/std of K noisy ranges (what the firmware shares)."""
    n = len(x)
    samples = distances(x)[None] + sigma * rng.standard_normal((k, n, n))
    mean, std = samples.mean(0), samples.std(0, ddof=1)
    np.fill_diagonal(mean, np.nan)
    count = np.full((n, n), k)
    np.fill_diagonal(count, 0)
    return RangeMatrix(mean, std, count)


@pytest.mark.parametrize("dim, n", [(2, 5), (3, 6)])
def test_calibration_covariance_is_honest_nees(dim, n):
    rng = np.random.default_rng(2024)
    sigma, k, trials = 0.06, 5, 400
    x = rng.uniform(0, 10, (n, dim))
    rot, trans = paper_frame(x)
    truth = x @ rot.T + trans
    nees = []
    for _ in range(trials):
        res = calibrate_anchors(_round(x, rng, sigma, k), dim=dim, range_std_m=sigma)
        free = np.diag(res.covariance) > 0
        e = (res.positions - truth).ravel()[free]
        nees.append(e @ np.linalg.solve(res.covariance[np.ix_(free, free)], e))
    dof = int(free.sum())
    total = float(np.sum(nees))
    lo, hi = stats.chi2.ppf([0.005, 0.995], trials * dof)
    assert lo < total < hi, (total / trials, dof)


def test_tag_covariance_is_honest_nees_and_matches_crlb():
    rng = np.random.default_rng(7)
    sigma, trials = 0.06, 2000
    anchors = np.array([[0, 0], [10, 0], [10, 8], [0, 8.0]])
    tag = np.array([[3.0, 4.0]])
    truth = distances(np.vstack([anchors, tag]))[-1, :4]
    ranges = truth + sigma * rng.standard_normal((trials, 4))
    fix = locate_tags(anchors, ranges, sigma)
    assert (fix.status == OK).all()
    err = fix.positions - tag
    nees = np.einsum("ti,tij,tj->t", err, np.linalg.inv(fix.covariance), err)
    lo, hi = stats.chi2.ppf([0.005, 0.995], trials * 2)
    assert lo < nees.sum() < hi
    bound = crlb_tags(anchors, tag, sigma)[0]
    empirical = np.cov(err.T)
    assert np.trace(empirical) / np.trace(bound) == pytest.approx(1.0, abs=0.1)


def test_anchor_crlb_paper_gauge_equals_solver_covariance_at_truth(rng):
    x = rng.uniform(0, 10, (5, 2))
    res = calibrate_anchors(distances(x), range_std_m=0.06)
    bound = crlb_anchors(x, 0.06**2)
    np.testing.assert_allclose(res.covariance, bound, atol=1e-10)
    free_bound = crlb_anchors(x, 0.06**2, gauge="free")
    # the frame-free bound spreads over all coordinates and has the 3 gauge modes removed
    assert np.linalg.matrix_rank(free_bound, tol=1e-12) == 5 * 2 - 3


def test_robust_loss_resists_nlos_outliers():
    rng = np.random.default_rng(3)
    x = rng.uniform(0, 10, (8, 2))
    d = distances(x) + 0.03 * rng.standard_normal((8, 8))
    d = (d + d.T) / 2
    d[0, 5] = d[5, 0] = d[0, 5] + 2.5  # NLOS outliers
    d[3, 7] = d[7, 3] = d[3, 7] + 1.8
    plain = calibrate_anchors(d, range_std_m=0.03)
    robust = calibrate_anchors(d, range_std_m=0.03, loss="cauchy")
    assert aligned_errors(robust.positions, x).mean() < 0.3 * aligned_errors(plain.positions, x).mean()
    # both outliers are named and left out; the fit on the rest is explained by the noise
    assert {tuple(p) for p in robust.rejected_pairs.tolist()} == {(0, 5), (3, 7)}
    assert robust.status == "ok" and robust.converged
    assert plain.status == "poor_fit" and not plain.converged
    kept = calibrate_anchors(d, range_std_m=0.03, loss="cauchy", reject_outliers=False)
    assert np.abs(kept.residuals_m).max() > 1.5 and len(kept.rejected_pairs) == 0


def test_mds_initializer_and_missing_pairs(rng):
    x = rng.uniform(0, 10, (7, 2))
    d = distances(x)
    d[2, 5] = d[5, 2] = np.nan
    d[0, 6] = d[6, 0] = np.nan  # trilateration needs ranges to 0: falls back to MDS
    res = calibrate_anchors(d, range_std_m=0.05)
    assert res.initializer in ("mds", "smacof", "buildup")  # the starts from the ranges alone
    rot, trans = paper_frame(x)
    np.testing.assert_allclose(res.positions, x @ rot.T + trans, atol=1e-6)
    assert len(res.pairs) == 21 - 2


def test_rigid_align_recovers_a_known_transform(rng):
    x = rng.normal(size=(6, 3))
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    y = x @ q.T + np.array([1.0, -2.0, 0.5])
    rot, trans = rigid_align(x, y)
    np.testing.assert_allclose(rot, q, atol=1e-9)
    np.testing.assert_allclose(x @ rot.T + trans, y, atol=1e-9)
    noisy = y + 0.1 * rng.normal(size=y.shape)
    rot, trans = rigid_align(x, noisy, pivot=2)
    np.testing.assert_allclose(x[2] @ rot.T + trans, noisy[2], atol=1e-12)  # the pivot maps exactly
    np.testing.assert_allclose(rot @ rot.T, np.eye(3), atol=1e-12)
    assert np.abs(rot - q).max() < 0.2  # and the rotation is still close to the true one



def _svd_rigid_align(source, target, w, allow_reflection, pivot):
    """The weighted Kabsch solution by SVD (what rigid_align computed before its 2D closed form)."""
    if pivot is None:
        mu_s, mu_t = (w[:, None] * source).sum(0) / w.sum(), (w[:, None] * target).sum(0) / w.sum()
    else:
        mu_s, mu_t = source[pivot], target[pivot]
    u, _, vt = np.linalg.svd(((target - mu_t) * w[:, None]).T @ (source - mu_s))
    d = np.ones(source.shape[1])
    if not allow_reflection and np.linalg.det(u @ vt) < 0:
        d[-1] = -1.0
    rot = (u * d) @ vt
    return rot, mu_t - mu_s @ rot.T


def test_planar_rigid_align_closed_form_equals_the_svd(rng):
    """2D alignment is solved in closed form (compiled): the SVD's answer for every weighting,
    pivot and reflection option, mirrored targets included."""
    for trial in range(400):
        n = int(rng.integers(3, 9))
        x = rng.normal(size=(n, 2)) * 5.0
        q, _ = np.linalg.qr(rng.normal(size=(2, 2)))  # a rotation or a reflection
        y = x @ q.T + rng.normal(size=2) + rng.uniform(0.0, 3.0) * rng.normal(size=(n, 2))
        w = rng.uniform(0.1, 2.0, n) if trial % 2 else np.ones(n)
        pivot = None if trial % 3 else int(rng.integers(n))
        reflect = bool(trial % 4)
        rot, trans = rigid_align(x, y, w, allow_reflection=reflect, pivot=pivot)
        want_rot, want_trans = _svd_rigid_align(x, y, w, reflect, pivot)
        np.testing.assert_allclose(rot, want_rot, atol=1e-9)
        np.testing.assert_allclose(trans, want_trans, atol=1e-9)
    with pytest.raises(np.linalg.LinAlgError):  # non-finite points: numpy's error, as before
        rigid_align(np.full((3, 2), np.nan), np.zeros((3, 2)))


def test_planar_rigid_align_edge_cases_behave_as_numpy_indexing_and_errors(rng):
    """The compiled 2D path keeps the numpy definitions at the edges (found by a review):
    a negative pivot counts from the end, an out-of-range pivot or reference is an IndexError
    (not an out-of-bounds read), weights summing to zero are numpy's LinAlgError."""
    x = rng.normal(size=(5, 2))
    y = x @ np.array([[0.0, -1.0], [1.0, 0.0]]).T + 1.0 + 0.05 * rng.normal(size=(5, 2))
    rot, trans = rigid_align(x, y, pivot=-1)
    np.testing.assert_allclose(x[4] @ rot.T + trans, y[4], atol=1e-12)  # the last point maps exactly
    with pytest.raises(IndexError):
        rigid_align(x, y, pivot=5)
    with pytest.raises(IndexError):
        paper_frame(x, (0, 7))
    with pytest.raises(np.linalg.LinAlgError):
        rigid_align(x, y, weights=np.zeros(5))


def test_planar_paper_frame_rules(rng):
    x = rng.normal(size=(5, 2)) * 4.0
    rot, trans = paper_frame(x, (1, 3))
    f = x @ rot.T + trans
    np.testing.assert_allclose(f[1], 0.0, atol=1e-12)  # refs[0] at the origin
    assert abs(f[3, 1]) < 1e-12 and f[3, 0] > 0  # refs[1] on +x
    assert f[:, 1].sum() > 0  # the rest to +y
    np.testing.assert_allclose(rot @ rot.T, np.eye(2), atol=1e-12)
    with pytest.raises(GeometryError, match="coincide"):
        paper_frame(np.array([[0.0, 0.0], [0.0, 0.0], [1.0, 1.0]]), (0, 1))
    with pytest.raises(GeometryError, match="collinear"):
        paper_frame(np.array([[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]]), (0, 1))

# -- errors -------------------------------------------------------------------------------------
def test_too_few_anchors():
    with pytest.raises(TooFewAnchorsError):
        calibrate_anchors(distances(np.eye(2)), range_std_m=0.05)
    with pytest.raises(TooFewAnchorsError):
        calibrate_anchors(distances(np.eye(3)), dim=3, range_std_m=0.05)


@pytest.mark.parametrize("bad", [-5.0, np.inf])
def test_invalid_ranges(bad, rng):
    d = distances(rng.uniform(0, 10, (4, 2)))
    d[1, 2] = bad
    with pytest.raises(InvalidRangeError, match=r"\(1, 2\)"):
        calibrate_anchors(d, range_std_m=0.05)


def test_range_matrix_with_nan_but_count_is_invalid(rng):
    m = _round(rng.uniform(0, 10, (4, 2)), rng, 0.05, 5)
    m.mean_m[0, 3] = np.nan
    with pytest.raises(InvalidRangeError):
        calibrate_anchors(m)


def test_disconnected_graph():
    x = np.array([[0, 0], [5, 0], [0, 5], [20, 20], [25, 20.0]])
    d = distances(x)
    d[:3, 3:] = np.nan
    d[3:, :3] = np.nan
    with pytest.raises(DisconnectedGraphError, match=r"\[0, 1, 2\]"):
        calibrate_anchors(d, range_std_m=0.05)


def test_coincident_and_collinear_anchors():
    with pytest.raises(GeometryError):
        calibrate_anchors(distances(np.array([[0, 0], [0, 0], [3, 4], [5, 1.0]])), range_std_m=0.05)
    # four anchors on a line: two offsets from it fixed only to second order, along no
    # particular pair of directions (the null space's basis is arbitrary): no honest covariance
    with pytest.raises(GeometryError):
        calibrate_anchors(distances(np.array([[0, 0], [1, 0], [2, 0], [5, 0.0]])), range_std_m=0.05)
    with pytest.raises(GeometryError):  # coplanar anchors cannot fix a 3D frame (two heights free)
        flat = np.array([[0, 0, 0], [4, 0, 0], [0, 4, 0], [4, 4, 0], [2, 1, 0.0]])
        calibrate_anchors(distances(flat), dim=3, range_std_m=0.05)


def test_tag_status_codes():
    anchors = np.array([[0, 0], [10, 0], [10, 8], [0, 8.0]])
    ranges = np.array([[5.0, 7.0, np.nan, np.nan], [3.0, 8.0, 9.0, 5.0]])
    fix = locate_tags(anchors, ranges, 0.06)
    assert fix.status[0] == TOO_FEW_RANGES and np.isnan(fix.positions[0]).all()
    assert fix.status[1] == OK
    collinear = np.array([[0, 0], [5, 0], [10, 0.0]])
    fix = locate_tags(collinear, np.array([[5.0, 3.0, 6.0]]), 0.06)
    assert fix.status[0] == DEGENERATE


def test_anchor_covariance_inflates_tag_covariance():
    anchors = np.array([[0, 0], [10, 0], [10, 8], [0, 8.0]])
    tag = np.array([[4.0, 3.0]])
    ranges = distances(np.vstack([anchors, tag]))[-1:, :4]
    plain = locate_tags(anchors, ranges, 0.06)
    infl = locate_tags(anchors, ranges, 0.06, anchor_covariance=np.tile(0.2**2 * np.eye(2), (4, 1, 1)))
    assert np.trace(infl.covariance[0]) > 5 * np.trace(plain.covariance[0])
    np.testing.assert_allclose(infl.positions, plain.positions, atol=1e-9)


def _reflect(p, a, b):
    u = (b - a) / np.linalg.norm(b - a)
    v = p - a
    return a + 2 * (v @ u) * u - v


def test_later_calibration_restarts_from_the_ranges_when_the_prior_is_folded():
    x = np.array([[0.0, 0.0], [6.0, 0.0], [6.0, 5.0], [0.0, 5.0]])
    prior = x.copy()
    prior[2] = _reflect(x[2], x[1], x[3])  # anchor 2 mirrored across the line 1-3
    from uwb_env.localization.calibration import _gauge_refs, _pair_data, _Problem

    pairs, dist, var, n = _pair_data(distances(x), 0.05, 0.03)
    stuck = _Problem(pairs, dist, var, n, 2, "linear", 2.0, 50, 1e-3).solve(_gauge_refs(prior), prior, "prior")
    assert stuck.out.converged and not stuck.fit_ok  # the warm start alone converges, folded
    # the fit test alone (no residual threshold) triggers the restarts from the ranges
    res = calibrate_anchors(distances(x), prior=prior, range_std_m=0.05, restart_sigmas=np.inf)
    assert res.initializer.startswith("prior+") and res.status == "ok"
    assert aligned_errors(res.positions, x).max() < 1e-6


def test_tag_tracking_restarts_a_warm_start_stuck_in_a_mirror_minimum():
    anchors = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]])
    tag = np.array([[2.0, 3.0]])
    ranges = np.linalg.norm(anchors - tag, axis=1)[None]
    wrong = np.array([[8.0, 7.0]])  # far side of the diagonal: a bad warm start
    stuck = locate_tags(anchors, ranges, 0.05, initial=wrong, max_iterations=1)
    assert np.linalg.norm(stuck.positions - tag) > 0.5
    fixed = locate_tags(anchors, ranges, 0.05, initial=wrong, max_iterations=1, restart_residual_m=0.3)
    np.testing.assert_allclose(fixed.positions, tag, atol=1e-6)
