"""Per-anchor round solver: one anchor re-locates against the others."""

import numpy as np
import pytest
from scipy.special import chdtri

from uwb_env.localization import InvalidRangeError
from uwb_env.localization.errors import SolverArgumentError
from uwb_env.localization.relocation import RelocationModel, relocate_anchor


def test_jacobian_matches_finite_differences():
    rng = np.random.default_rng(0)
    for dim in (2, 3):
        model = RelocationModel(rng.uniform(0, 10, (5, dim)))
        p = rng.uniform(0, 10, dim)
        np.testing.assert_allclose(model.jacobian(p), model.jacobian_fd(p), atol=1e-7)


def test_recovers_the_anchor_with_a_consistent_covariance():
    rng = np.random.default_rng(1)
    others = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]])
    truth = np.array([3.0, 4.0])
    sigma = 0.03
    nees, statuses = [], []
    for _ in range(300):
        r = np.linalg.norm(others - truth, axis=1) + sigma * rng.standard_normal(4)
        res = relocate_anchor(r, others, sigma**2, prior=truth + rng.normal(0, 0.5, 2),
                              prior_covariance=0.25 * np.eye(2))
        statuses.append(res.status)
        e = res.position - truth
        nees.append(e @ np.linalg.solve(res.covariance, e))
    assert np.mean(nees) == pytest.approx(2.0, rel=0.2)
    assert statuses.count("ok") >= 295  # the fit test's 1e-3 false alarms, nothing more


def test_others_covariance_inflates_the_uncertainty():
    others = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]])
    r = np.linalg.norm(others - np.array([3.0, 4.0]), axis=1)
    sharp = relocate_anchor(r, others, 0.03**2)
    blurred = relocate_anchor(r, others, 0.03**2, others_covariance=np.tile(0.2**2 * np.eye(2), (4, 1, 1)))
    assert np.trace(blurred.covariance) > 10 * np.trace(sharp.covariance)


def test_mirror_of_collinear_others_is_ambiguous_without_a_prior_and_decided_with_one():
    others = np.array([[0.0, 0.0], [5.0, 0.05], [10.0, 0.0]])  # nearly on a line
    truth = np.array([4.0, 3.0])
    r = np.linalg.norm(others - truth, axis=1)
    res = relocate_anchor(r, others, 0.03**2, prior=np.array([4.0, -0.5]), prior_covariance=25.0 * np.eye(2))
    assert res.status == "ambiguous" and res.alternative is not None
    decided = relocate_anchor(r, others, 0.03**2, prior=np.array([4.2, 2.8]), prior_covariance=0.1 * np.eye(2))
    assert decided.status == "ok"
    np.testing.assert_allclose(decided.position, truth, atol=0.05)


def test_3d_relocation_against_three_others_is_ambiguous_when_the_prior_cannot_pick_a_side():
    """Three ranges in 3D: the anchor and its mirror across the others' plane fit them exactly.
    With a vague height prior (a near-flat team's covariance, as on the three_d scenario's seed
    1,000,017) the two intersections, about 1.2 m apart, both lie inside the answer's
    covariance: the relocation used to pick one and report ok, on the wrong side in about half
    of the draws. Now an answer reported ok is consistent with its covariance (the noise can
    merge the two intersections into one minimum near the plane: that one is ok, with the
    prior's height spread) and a sharp prior decides."""
    rng = np.random.default_rng(2)
    tilt = np.linalg.qr(np.array([[1.0, 0.2, 0.3], [-0.2, 1.0, 0.25], [0.1, -0.3, 1.0]]))[0]  # a tilted plane
    others = np.array([[0.0, 0.0, 0.0], [8.0, 0.0, 0.0], [1.0, 8.0, 0.0]]) @ tilt.T
    truth = np.array([6.0, 2.0, 0.6]) @ tilt.T  # 0.6 m off the others' plane
    var = 0.0045
    bound = chdtri(3, 1e-3)
    for height_var, prior_height in ((5.1, 0.0), (5.1, 0.1), (5.1, 0.3), (0.01, 0.6)):
        prior = np.array([6.05, 1.95, prior_height]) @ tilt.T  # 0.0: on the plane, its own mirror
        cov = tilt @ np.diag([0.05, 0.05, height_var]) @ tilt.T
        statuses = []
        for _ in range(60):
            r = np.linalg.norm(others - truth, axis=1) + rng.normal(0.0, np.sqrt(var), 3)
            res = relocate_anchor(r, others, var, prior=prior, prior_covariance=cov)
            statuses.append(res.status)
            if res.ok:
                e = res.position - truth
                assert e @ np.linalg.solve(res.covariance, e) < bound, (prior_height, res.position)
            if res.status == "ambiguous":  # the other intersection, on the other side of the plane
                sides = [float(((p - others[0]) @ tilt)[2]) for p in (res.position, res.alternative)]
                assert sides[0] * sides[1] < 0, sides
        if height_var < 1.0:
            assert statuses.count("ok") == 60
        else:  # 41-48 of 60 over seeds 0-19 (the rest: one minimum left near the plane, or not converged)
            assert statuses.count("ambiguous") >= 39, statuses


def test_a_start_on_the_others_plane_does_not_stop_at_the_saddle():
    """A prior on the plane of three others is its own mirror, and Gauss-Newton from it stays on
    the plane (the saddle between the two intersections, by symmetry): the solver must still
    find both intersections (noise-free ranges) and report the ambiguity, not the saddle."""
    others = np.array([[0.0, 0.0, 0.0], [8.0, 0.0, 0.0], [1.0, 8.0, 0.0]])
    truth = np.array([6.0, 2.0, 0.6])
    r = np.linalg.norm(others - truth, axis=1)
    res = relocate_anchor(r, others, 0.0045, prior=np.array([6.0, 2.0, 0.0]),
                          prior_covariance=np.diag([0.05, 0.05, 5.1]))
    assert res.status == "ambiguous"
    np.testing.assert_allclose(sorted([res.position[2], res.alternative[2]]), [-0.6, 0.6], atol=0.05)


def test_a_rival_that_settles_slowly_still_counts():
    """Near the others' plane Gauss-Newton can take 20-25 steps to settle; with a budget of 20
    the other intersection came back unconverged, was dropped as a rival, and this draw (from a
    review's near-plane generator) was reported ok on the wrong side with NEES 23.9."""
    others = np.array([[2.2607078726658507, -5.470304362613103, 0.0], [7.983211965664845, 5.984549144573608, 0.0],
                       [7.5023983373860315, -5.128190266750549, 0.0]])
    r = np.array([6.499981917830373, 6.595121362602516, 5.069209834151192])
    prior = np.array([6.110063070700781, -0.18521097720066426, -0.4203564946137932])
    res = relocate_anchor(r, others, 0.00245803508430186, prior=prior, prior_covariance=np.diag([0.04, 0.04, 1.0]),
                          others_covariance=np.tile(0.06**2 * np.eye(3), (3, 1, 1)))
    assert res.status == "ambiguous"
    assert res.position[2] * res.alternative[2] < 0  # the two intersections, either side of z = 0


def test_a_start_that_settles_on_its_last_iteration_has_converged():
    others = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]])
    r = np.linalg.norm(others - np.array([3.0, 4.0]), axis=1) + np.array([0.02, -0.01, 0.015, -0.02])
    free = relocate_anchor(r, others, 0.03**2, max_iterations=200)
    assert free.ok
    tight = relocate_anchor(r, others, 0.03**2, max_iterations=free.iterations)
    assert tight.status == "ok" and tight.iterations == free.iterations
    np.testing.assert_allclose(tight.position, free.position)


def test_inconsistent_ranges_are_a_poor_fit():
    others = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0], [5.0, -3.0]])
    r = np.linalg.norm(others - np.array([3.0, 4.0]), axis=1)
    r[2] += 2.0  # NLOS
    assert relocate_anchor(r, others, 0.03**2).status == "poor_fit"


def test_bad_input_is_a_typed_error():
    others = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]])
    r = np.array([5.0, 6.0, 7.0])
    with pytest.raises(InvalidRangeError, match="ranges_m"):
        relocate_anchor(np.array([5.0, np.inf, 7.0]), others, 0.01)
    with pytest.raises(SolverArgumentError, match="range_var_m2"):
        relocate_anchor(r, others, 0.0)
    with pytest.raises(SolverArgumentError, match="prior"):
        relocate_anchor(r, others, 0.01, prior=np.zeros(2))
