"""Per-anchor round solver: one anchor re-locates against the others."""

import numpy as np
import pytest

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
