"""The batched stuck-tag refit (one call for every copy) agrees with the per-copy refit."""

import numpy as np

from uwb_env.localization.multilateration import refit_stuck_tags, refit_stuck_tags_2d


def test_batched_refit_rescues_the_same_tags_as_the_per_copy_refit():
    rng = np.random.default_rng(0)
    S, N, M, sigma = 64, 4, 3, 0.05
    anchors = rng.uniform(0, 10, (S, N, 2))
    tags = rng.uniform(2, 8, (S, M, 2))
    ranges = np.linalg.norm(tags[:, :, None] - anchors[:, None], axis=-1) + rng.normal(0, sigma, (S, M, N))
    ranges = np.maximum(ranges, 0.0)
    ranges[rng.random((S, M, N)) < 0.05] = np.nan  # dropouts
    # tracked fixes: most right, a quarter stuck far off (a wrong minimum)
    positions = tags + rng.normal(0, 0.02, tags.shape)
    stuck = rng.random((S, M)) < 0.25
    positions[stuck] += rng.uniform(-6, 6, (int(stuck.sum()), 2))
    fitted = np.linalg.norm(positions[:, :, None] - anchors[:, None], axis=-1)
    rms = np.sqrt(np.nanmean((fitted - ranges) ** 2, axis=-1))
    threshold = np.full(S, 0.3)

    batched_pos, batched_rms = positions.copy(), rms.copy()
    refit_stuck_tags_2d(anchors, ranges, batched_pos, batched_rms, threshold, sigma**2)
    single_pos, single_rms = positions.copy(), rms.copy()
    for k in range(S):
        refit_stuck_tags(anchors[k], ranges[k], single_pos[k], single_rms[k], threshold[k], sigma)

    enough = np.isfinite(ranges).sum(-1) >= 3
    err_b = np.linalg.norm(batched_pos - tags, axis=-1)[enough]
    err_s = np.linalg.norm(single_pos - tags, axis=-1)[enough]
    assert (np.linalg.norm(positions - tags, axis=-1)[enough] > 1.0).sum() > 20  # there was work to do
    assert (err_b < 0.3).mean() >= (err_s < 0.3).mean() - 0.02  # as many tags rescued
    assert (err_b < 0.3).mean() > 0.95
    assert np.all(batched_rms[enough] <= rms[enough] + 1e-12)  # never worse than the tracked fix


def test_one_singular_system_does_not_fail_the_batch(monkeypatch):
    """numpy's batched solve raises for the whole batch when one system is singular (seen in
    the vector-env benchmark); the refit then solves row by row and leaves that tag alone."""
    import uwb_env.localization.multilateration as mod

    real_solve = np.linalg.solve

    def solve(a, b):
        if a.ndim == 3:
            raise np.linalg.LinAlgError("Singular matrix")
        return real_solve(a, b)

    monkeypatch.setattr(mod.np.linalg, "solve", solve)
    anchors = np.array([[[0, 0], [10, 0], [0, 10], [10, 10]]], float).repeat(2, 0)
    ranges = np.array([[[7.07, 7.07, 7.07, 7.07]], [[5.0, 8.0, 8.0, 11.0]]])
    pos, rms = np.full((2, 1, 2), np.nan), np.full((2, 1), np.inf)
    mod.refit_stuck_tags_2d(anchors, ranges, pos, rms, np.zeros(2), 0.0036)
    assert np.isfinite(pos).all()
