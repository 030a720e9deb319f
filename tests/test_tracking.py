"""The planar tag tracker: the numpy kernel (many groups) and the scalar one (one small group)."""

import numpy as np
import pytest

from uwb_env.localization.multilateration import SMALL_TRACKING_WORK, _track_small_2d, track_tags_2d


def _case(rng, n_tags=3, n_anchors=4, missing=0):
    anchors = rng.uniform(0, 20, (n_anchors, 2))
    tags = rng.uniform(2, 18, (n_tags, 2))
    ranges = np.linalg.norm(tags[:, None] - anchors[None], axis=-1) + 0.06 * rng.standard_normal((n_tags, n_anchors))
    ranges[0, 0] += 1.5  # an NLOS-like outlier for the robust losses to down-weight
    flat = ranges.ravel()
    flat[rng.choice(flat.size, missing, replace=False)] = np.nan
    cov = np.stack([np.diag(rng.uniform(0.001, 0.02, 2)) for _ in range(n_anchors)])
    cov[:, 0, 1] = cov[:, 1, 0] = 0.003
    previous = tags + rng.normal(0, 0.3, tags.shape)
    return anchors, previous, ranges, cov


@pytest.mark.parametrize("loss", ["linear", "huber", "soft_l1", "cauchy", "nlos"])
@pytest.mark.parametrize("with_cov", [False, True])
@pytest.mark.parametrize("missing", [0, 3, 6])
def test_scalar_kernel_matches_the_numpy_kernel(loss, with_cov, missing, rng):
    anchors, previous, ranges, cov = _case(rng, missing=missing)
    cov_arg = cov if with_cov else None
    small = _track_small_2d(anchors, previous, ranges, 0.0036, cov_arg, loss, 3.0, 2)
    # two identical groups take the numpy path
    two = track_tags_2d(np.stack([anchors] * 2), np.stack([previous] * 2), np.stack([ranges] * 2), 0.0036,
                        None if cov_arg is None else np.stack([cov] * 2), loss, 3.0, 2)
    for got, want in zip(small, two, strict=True):
        np.testing.assert_allclose(got[0], want[0], rtol=1e-9, atol=1e-12, equal_nan=True)
    # a tag left with fewer than 3 ranges has no fix
    few = np.isfinite(ranges).sum(1) < 3
    assert np.isnan(small[0][0][few]).all() and np.isfinite(small[0][0][~few]).all()


def test_dispatch_uses_the_scalar_kernel_for_one_small_group_only(rng, monkeypatch):
    import uwb_env.localization.multilateration as mod

    calls = []
    real = mod._track_small_2d
    monkeypatch.setattr(mod, "_track_small_2d", lambda *a: calls.append(1) or real(*a))
    anchors, previous, ranges, _ = _case(rng)
    mod.track_tags_2d(anchors[None], previous[None], ranges[None], 0.0036, iterations=2)
    assert calls == [1]
    big_tags = SMALL_TRACKING_WORK // 4 + 1  # 4 anchors, 1 iteration: just over the limit
    anchors, previous, ranges, _ = _case(rng, n_tags=big_tags)
    mod.track_tags_2d(anchors[None], previous[None], ranges[None], 0.0036, iterations=1)
    assert calls == [1]


def test_tracking_converges_on_moving_tags(rng):
    anchors = np.array([[0, 0], [20, 0], [20, 20], [0, 20.0]])
    tags = np.array([[5.0, 5.0], [12.0, 9.0], [15.0, 16.0]])
    fix = tags + 0.5
    errors = []
    for _ in range(30):
        tags = tags + rng.normal(0, 0.05, tags.shape)
        ranges = np.linalg.norm(tags[:, None] - anchors[None], axis=-1) + 0.05 * rng.standard_normal((3, 4))
        fix, rms, res = track_tags_2d(anchors[None], fix[None], ranges[None], 0.05**2, loss="huber")
        fix = fix[0]
        errors.append(np.linalg.norm(fix - tags, axis=1).max())
        assert res.shape == (1, 3, 4) and np.all(rms[0] < 0.2)
    assert max(errors[5:]) < 0.15


def test_mirror_check_switches_a_rejected_fix_and_flags_a_true_ambiguity():
    from uwb_env.localization.multilateration import TAG_AMBIGUOUS, TAG_OK, check_mirror_2d

    var = 0.03**2
    # well-spread anchors: a warm start stuck at the mirror across the principal axis is rejected
    anchors = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 6.0], [0.0, 6.0]])
    tag = np.array([2.0, 1.0])
    ranges = np.linalg.norm(anchors - tag, axis=1)
    centre = anchors.mean(0)
    wrong = np.array([tag[0], 2 * centre[1] - tag[1]])  # mirror across the long axis y = 3
    pos, status, switched = check_mirror_2d(anchors[None], wrong[None, None], ranges[None, None], var)
    assert switched[0, 0] and status[0, 0] == TAG_OK
    np.testing.assert_allclose(pos[0, 0], tag, atol=1e-3)
    # near-collinear anchors: both sides fit within the noise -> ambiguous, not a confident fix
    line = np.array([[0.0, 0.0], [5.0, 0.01], [10.0, 0.0], [15.0, 0.01]])
    tag = np.array([7.0, 3.0])
    ranges = np.linalg.norm(line - tag, axis=1)
    pos, status, switched = check_mirror_2d(line[None], tag[None, None], ranges[None, None], var)
    assert status[0, 0] == TAG_AMBIGUOUS and not switched[0, 0]
    # an unambiguous fix stays ok
    pos, status, switched = check_mirror_2d(anchors[None], np.array([[[2.0, 1.0]]]),
                                            np.linalg.norm(anchors - [2.0, 1.0], axis=1)[None, None], var)
    assert status[0, 0] == TAG_OK and not switched.any()
