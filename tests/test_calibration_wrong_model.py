"""A round whose misfit is spread over the whole shape (a wrong model: robots that moved
through a long round) is reported as a poor fit without spending one solve per dropped pair or
per reflected anchor; a round with a few outliers still gets them rejected."""

import numpy as np

import uwb_env.localization.calibration as calibration
from uwb_env.localization import aligned_errors, calibrate_anchors


def _count_solves(monkeypatch):
    calls = []
    solve = calibration._Problem.solve

    def counted(self, *args, **kwargs):
        calls.append(args[2] if len(args) > 2 else kwargs.get("name"))
        return solve(self, *args, **kwargs)

    monkeypatch.setattr(calibration._Problem, "solve", counted)
    return calls


def _ranges(x, rng, sigma):
    d = np.linalg.norm(x[:, None] - x[None], axis=2)
    noise = rng.normal(0, sigma, d.shape)
    d = d + np.triu(noise, 1) + np.triu(noise, 1).T
    return d


def test_spread_misfit_is_a_poor_fit_without_rejection_solves(monkeypatch):
    rng = np.random.default_rng(3)
    n, sigma = 40, 0.05
    x = rng.uniform(0, 30, (n, 2))
    d = _ranges(x, rng, sigma)
    # each pair measured at a different moment of a long round: every anchor moved up to 1.5 m
    d = d + rng.uniform(-1.5, 1.5, d.shape)
    d = np.triu(d, 1) + np.triu(d, 1).T
    calls = _count_solves(monkeypatch)
    result = calibrate_anchors(d, range_std_m=sigma, loss="cauchy", reject_outliers=True)
    assert result.status == "poor_fit"
    assert not result.converged
    assert len(result.rejected_pairs) == 0
    # starts (+ at most the unfold passes), not one solve per candidate drop (2N = 80)
    assert len(calls) < 40, calls


def test_few_outliers_are_still_rejected():
    rng = np.random.default_rng(4)
    n, sigma = 12, 0.05
    x = rng.uniform(0, 20, (n, 2))
    d = _ranges(x, rng, sigma)
    for i, j in ((0, 5), (3, 7), (2, 9)):
        d[i, j] = d[j, i] = d[i, j] + 2.0  # NLOS: longer
    result = calibrate_anchors(d, range_std_m=sigma, loss="cauchy", reject_outliers=True)
    assert result.status == "ok"
    assert {tuple(p) for p in result.rejected_pairs.tolist()} >= {(0, 5), (3, 7), (2, 9)}
    assert aligned_errors(result.positions, x).max() < 0.2
