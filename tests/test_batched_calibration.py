"""Batched later calibrations give the full solver's answers, and hand back what needs more."""

import numpy as np

from uwb_env.localization import calibrate_anchors
from uwb_env.localization.batched_calibration import calibrate_with_priors
from uwb_env.measurements import RangeMatrix

SIGMA = 0.06


def _round(x, rng, nlos=0.0):
    n = len(x)
    d = np.linalg.norm(x[:, None] - x[None], axis=-1)
    bias = np.triu((rng.random((n, n)) < nlos) * rng.exponential(0.5, (n, n)), 1)
    samples = d + bias + bias.T + SIGMA * rng.standard_normal((5, n, n))
    mean, std = samples.mean(0), samples.std(0, ddof=1)
    np.fill_diagonal(mean, np.nan)
    count = np.full((n, n), 5) - 5 * np.eye(n, dtype=int)
    return RangeMatrix(mean, std, count)


def test_batched_results_equal_the_full_solver_and_hard_cases_are_handed_back():
    rng = np.random.default_rng(3)
    teams = [rng.uniform(0, 12, (4, 2)) for _ in range(48)]
    matrices = [_round(x, rng, nlos=0.1) for x in teams]
    priors = np.stack([x + rng.normal(0, 0.2, x.shape) for x in teams])
    matrices[5].count[1, 2] = 0  # a missing pair: the full solver's business
    matrices[5].mean_m[1, 2] = np.nan
    batched = calibrate_with_priors(matrices, priors, SIGMA, "huber", 3.0, "prior")
    full = [calibrate_anchors(m, prior=p, range_std_m=SIGMA, loss="huber", f_scale=3.0, gauge="prior")
            for m, p in zip(matrices, priors, strict=True)]
    assert batched[5] is None
    handled = [k for k, b in enumerate(batched) if b is not None]
    assert len(handled) >= 24  # most rounds (10 % NLOS links make some fits poor)
    for k in handled:
        assert full[k].status == "ok"
        np.testing.assert_allclose(batched[k].positions, full[k].positions, atol=1e-6)
        np.testing.assert_allclose(batched[k].anchor_covariance(), full[k].anchor_covariance(), rtol=1e-4,
                                   atol=1e-12)
        assert abs(batched[k].chi2 - full[k].chi2) < 1e-6 and batched[k].dof == full[k].dof
    # every poorly fitting round is left to the full solver (which restarts, unfolds, reports)
    assert all(batched[k] is None for k in range(len(full)) if full[k].status != "ok")


def test_one_compiled_call_solves_each_team_as_alone_in_its_own_gauge():
    """Teams with different gauge anchors share one kernel call and its buffers: every team's
    answer equals the answer of a call with that team alone, and the array results hand back
    and convert as the list API does."""
    from uwb_env.localization._lm_kernel import LOSS_CODES, solve_teams_2d
    from uwb_env.localization.batched_calibration import (
        STATUS_NONE,
        TeamSolutions,
        _solve_teams,
        symmetric_arrays,
    )

    rng = np.random.default_rng(11)
    teams = [rng.uniform(0, 12, (5, 2)) for _ in range(40)]
    matrices = [_round(x, rng, nlos=0.15) for x in teams]
    priors = np.stack([x + rng.normal(0, 0.2, x.shape) for x in teams])
    complete, pairs, dist, var = symmetric_arrays(np.stack([m.mean_m for m in matrices]),
                                                  np.stack([m.count for m in matrices]), SIGMA)
    assert complete.all()
    ref = np.argmax(np.linalg.norm(priors - priors[:, :1], axis=2), axis=1).astype(np.int64)
    assert len(np.unique(ref)) >= 3  # the teams really use different gauges
    i, j = pairs[:, 0].astype(np.int64), pairs[:, 1].astype(np.int64)
    sqrt_iv = 1.0 / np.sqrt(var)
    together = solve_teams_2d(priors, ref, i, j, dist, sqrt_iv, LOSS_CODES["huber"], 3.0, 50)
    assert together[1].sum() >= 30
    for k in range(len(teams)):
        alone = solve_teams_2d(priors[k:k + 1], ref[k:k + 1], i, j, dist[k:k + 1], sqrt_iv[k:k + 1],
                               LOSS_CODES["huber"], 3.0, 50)
        assert alone[1][0] == together[1][k]
        if together[1][k]:
            for a, b in zip(together, alone, strict=True):
                np.testing.assert_array_equal(a[k], b[0])
    solved = _solve_teams(pairs, dist, var, priors, "huber", 3.0, "prior", 50, 1e-3, 8.0)
    assert isinstance(solved, TeamSolutions)
    listed = solved.results()
    for k, res in enumerate(listed):
        assert (res is None) == (solved.status[k] == STATUS_NONE)
    kept = np.flatnonzero(solved.status != STATUS_NONE)
    sub = solved.subset(kept)
    np.testing.assert_array_equal(sub.positions, solved.positions[kept])
    solved.hand_back(kept[:3])
    assert all(solved.result(k) is None for k in kept[:3])


def test_single_env_rounds_take_the_compiled_solve_and_get_the_full_solvers_answer(monkeypatch):
    # The single env solves a usual later round with the batched env's compiled solve (a team
    # of one, poor fits through the full solver's further steps batched) and hands the rest to
    # the full solver: every compiled answer must be the one the full solver gives for the same
    # round, prior and weights.
    import uwb_env.system as system_module
    import uwb_env.team_state as team_state
    from uwb_env.config import EnvConfig
    from uwb_env.measurements import RangeMatrix
    from uwb_env.system import LocalizationSystem

    compiled, full_calls, checked = [0], [0], [0]
    original_solve = system_module.solve_later_rounds
    original_full = team_state.calibrate_anchors

    def counting_full(*args, **kwargs):
        full_calls[0] += 1
        return original_full(*args, **kwargs)

    poor = [0]

    def checked_solve(mean, std, count, carry, est_mid, prior_std, solver, pair_range_std_m):
        out = original_solve(mean, std, count, carry, est_mid, prior_std, solver, pair_range_std_m)
        if out.compiled[0]:
            compiled[0] += 1
            poor[0] += out.fit[0] == team_state.FIT_POOR
            matrix = RangeMatrix(mean[0], std[0], count[0], None if carry is None else carry[0])
            ref = original_full(matrix, dim=2, prior=est_mid[0], gauge=solver.gauge, loss=solver.loss,
                                f_scale=solver.f_scale_sigmas, range_std_m=pair_range_std_m, prior_std_m=prior_std[0])
            assert team_state.CALIBRATION_FIT_NAMES[out.fit[0]] == ref.status
            assert not ref.ambiguous and not out.ambiguous[0]
            np.testing.assert_allclose(out.positions[0], ref.positions, atol=1e-6)
            np.testing.assert_allclose(out.anchor_cov[0], ref.anchor_covariance(), rtol=1e-4, atol=1e-12)
            assert abs(out.chi2[0] - ref.chi2) < 1e-6 * max(1.0, ref.chi2)
            assert abs(out.rms_m[0] - ref.rms_residual_m) < 1e-6
            checked[0] += 1
        return out

    monkeypatch.setattr(system_module, "solve_later_rounds", checked_solve)
    monkeypatch.setattr(team_state, "calibrate_anchors", counting_full)
    # a harsher radio, its NLOS excess left out of the weights: poor fits to check too
    env = LocalizationSystem(EnvConfig.from_dict({"sim": {"ranging": {"nlos_probability": 0.2}}}))
    env.pair_range_std_m = env.range_std_m
    env.reset(np.random.default_rng(4))
    full_calls[0] = 0  # (the first calibration, at reset, takes the full solver of uwb_env.system)
    requests = np.ones(env.n_anchors, dtype=bool)
    for t in range(400):
        env.step(requests if t % 10 == 0 else ~requests)
    assert env.calibration_count >= 30
    assert checked[0] == compiled[0] >= 25  # most rounds took the compiled solve, each checked
    assert poor[0] >= 2  # poor fits among them
    # every later calibration came from one of the two paths
    assert compiled[0] + full_calls[0] >= env.calibration_count - 1


def test_a_near_collinear_team_is_handed_back_as_the_full_solver_rejects_it():
    """Three anchors 10 m apart, the third 10-50 um off their line: J^T W J is positive definite
    but its condition number is ~1e-12, so the full solver reports the fit ``degenerate`` (the
    offset bounded only at second order) and the env does not apply it. The compiled team solve
    used to test positive definiteness alone and return "ok" with a 6.8e7 m^2 covariance; in
    per-anchor training the next relocation of such an anchor could not invert that prior and
    ``step()`` raised."""
    from uwb_env.localization.batched_calibration import STATUS_NONE, later_calibrations, symmetric_arrays
    from uwb_env.team_state import FIT_ERROR, RoundSolutions

    for h in (1e-5, 5e-5):
        x = np.array([[0.0, 0.0], [10.0, 0.0], [5.0, h]])
        d = np.linalg.norm(x[:, None] - x[None], axis=2)
        count = np.full((3, 3), 5) - 5 * np.eye(3, dtype=int)
        mean = d.copy()
        np.fill_diagonal(mean, np.nan)
        _, pairs, dist, var = symmetric_arrays(mean[None], count[None], 0.06)
        solved = later_calibrations(pairs, dist, var, x[None], "huber", 3.0, "anchor0")
        assert solved.status[0] == STATUS_NONE and solved.result(0) is None
        res = calibrate_anchors(RangeMatrix(mean, np.full((3, 3), 0.06), count), prior=x, range_std_m=0.06,
                                loss="huber", f_scale=3.0)
        assert res.status == "degenerate" and not res.converged
        std = res.position_std_m()
        assert np.all(np.isfinite(res.covariance)) and 0.05 < std[2] < 10.0  # bounded, not 8e3 m
        out = RoundSolutions(1, 3, 2)
        out.put_result(0, res)
        assert out.fit[0] == FIT_ERROR and not out.applicable[0] and "degenerate" in out.message[0]
