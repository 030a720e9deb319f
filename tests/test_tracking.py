"""The planar tag tracker (one compiled kernel for one env and for many copies), checked
against an independent numpy formulation of the same Gauss-Newton maths (points as complex
numbers: A z = (W z + S conj(z)) / 2 with W = sum w, S = sum w u^2)."""

import numpy as np
import pytest

from uwb_env.localization.multilateration import track_tags_2d
from uwb_env.localization.robust import irls_weights


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


def _reference(anchors, previous, ranges, var, cov, loss, f_scale, iterations):
    """One group, numpy, complex-number algebra (a formulation independent of the kernel's)."""
    a = anchors[:, 0] + 1j * anchors[:, 1]
    p = previous[:, 0] + 1j * previous[:, 1]
    valid = np.isfinite(ranges)
    r = np.where(valid, ranges, 0.0)
    for _ in range(iterations):
        d = p[:, None] - a[None]
        dist = np.maximum(np.abs(d), 1e-12)
        u = d / dist
        res = dist - r
        extra = 0.0 if cov is None else (0.5 * (cov[:, 0, 0] + cov[:, 1, 1])
                                         + ((u * u) * (0.5 * (cov[:, 0, 0] - cov[:, 1, 1]) - 1j * cov[:, 0, 1])).real)
        iv = valid / (var + extra)
        w = iv if loss == "linear" else iv * irls_weights(res * np.sqrt(iv), loss, f_scale)
        tw, s2, g = w.sum(1), (w * u * u).sum(1), (w * res * u).sum(1)
        det = tw * tw - np.abs(s2) ** 2
        p = p - (tw * g - s2 * g.conj()) * 2.0 / np.where(det > 1e-300, det, np.inf)
    res = np.where(valid, np.abs(p[:, None] - a[None]) - r, np.nan)
    count = valid.sum(1)
    rms = np.sqrt(np.nansum(res * res, 1) / np.maximum(count, 1))
    pos = np.stack([p.real, p.imag], -1)
    bad = (count < 3) | ~np.isfinite(rms)
    pos[bad], rms[bad], res[bad] = np.nan, np.nan, np.nan
    return pos, rms, res


@pytest.mark.parametrize("loss", ["linear", "huber", "soft_l1", "cauchy", "nlos"])
@pytest.mark.parametrize("with_cov", [False, True])
@pytest.mark.parametrize("missing", [0, 3, 6])
def test_kernel_matches_the_reference_for_one_and_many_groups(loss, with_cov, missing, rng):
    groups = [_case(rng, missing=missing) for _ in range(3)]
    var = np.array([0.0036, 0.0025, 0.01])
    stack = [np.stack([g[i] for g in groups]) for i in range(4)]
    cov_arg = stack[3] if with_cov else None
    many = track_tags_2d(stack[0], stack[1], stack[2], var, cov_arg, loss, 3.0, 2)
    for k, (anchors, previous, ranges, cov) in enumerate(groups):
        want = _reference(anchors, previous, ranges, var[k], cov if with_cov else None, loss, 3.0, 2)
        one = track_tags_2d(anchors[None], previous[None], ranges[None], var[k], cov[None] if with_cov else None,
                            loss, 3.0, 2)
        for got_one, got_many, w in zip(one, many, want, strict=True):
            np.testing.assert_allclose(got_one[0], w, rtol=1e-9, atol=1e-12, equal_nan=True)
            np.testing.assert_allclose(got_many[k], w, rtol=1e-9, atol=1e-12, equal_nan=True)
        # a tag left with fewer than 3 ranges has no fix
        few = np.isfinite(ranges).sum(1) < 3
        assert np.isnan(one[0][0][few]).all() and np.isfinite(one[0][0][~few]).all()


def test_a_tag_without_a_fix_stays_without_one(rng):
    anchors, previous, ranges, _ = _case(rng)
    previous[1] = np.nan
    pos, rms, res = track_tags_2d(anchors[None], previous[None], ranges[None], 0.0036)
    assert np.isnan(pos[0, 1]).all() and np.isnan(rms[0, 1]) and np.isnan(res[0, 1]).all()
    assert np.isfinite(pos[0, [0, 2]]).all()


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


def _reference_mirror(anchors, positions, ranges, var, cov, loss, f_scale, margin=10.83, iterations=3):
    """One group's mirror check in numpy complex algebra (independent of the compiled kernel)."""
    positions = positions.copy()
    m = len(positions)
    status, switched = np.zeros(m, np.int8), np.zeros(m, bool)
    fixed = np.isfinite(positions).all(-1)
    status[~fixed] = 2
    za = anchors[:, 0] + 1j * anchors[:, 1]
    centre = za.mean()
    d = za - centre
    turn = np.exp(1j * np.angle((d * d).sum()))
    zp = positions[:, 0] + 1j * positions[:, 1]
    zm = centre + turn * np.conj(zp - centre)

    def chi2(z):
        res = np.abs(z[:, None] - za[None]) - ranges
        return np.nansum(res * res, -1) / var, np.isfinite(res).sum(-1)

    c_fix, n_valid = chi2(zp)
    c_raw, _ = chi2(zm)
    candidate = (fixed & (n_valid >= 3) & (c_raw < c_fix + margin + 50.0 * n_valid)
                 & (np.abs(zm - zp) > 3 * np.sqrt(var)))
    start = np.where(candidate[:, None], np.stack([zm.real, zm.imag], -1), np.nan_to_num(positions))
    refined = _reference(anchors, start, ranges, var, cov, loss, f_scale, iterations)[0]
    zr = refined[:, 0] + 1j * refined[:, 1]
    c_mir, _ = chi2(zr)
    ok = candidate & np.isfinite(c_mir) & (np.abs(zr - zp) > 3 * np.sqrt(var))
    better = ok & (c_mir < c_fix - margin)
    tie = ok & ~better & (np.abs(c_mir - c_fix) <= margin)
    positions[better] = refined[better]
    switched |= better
    status[tie] = 1
    return positions, status, switched


@pytest.mark.parametrize("loss", ["linear", "cauchy", "nlos"])
@pytest.mark.parametrize("with_cov", [False, True])
def test_mirror_kernel_matches_the_reference(loss, with_cov, rng):
    from uwb_env.localization.multilateration import check_mirror_2d

    groups, outcomes = [], set()
    for g in range(40):
        # near-collinear anchors (the mirror is a real candidate) and tags on either side
        anchors = np.column_stack([rng.uniform(0, 20, 4), rng.normal(0, 0.3 + 0.1 * (g % 5), 4)])
        tags = np.column_stack([rng.uniform(0, 20, 5), rng.normal(0, 3, 5)])
        ranges = np.linalg.norm(tags[:, None] - anchors[None], axis=-1) + 0.03 * rng.standard_normal((5, 4))
        ranges[0, g % 4] = np.nan
        fixes = tags * np.array([1.0, -1.0 if g % 2 else 1.0]) + rng.normal(0, 0.05, tags.shape)
        fixes[4] = np.nan  # a tag without a fix
        cov = np.stack([np.diag(rng.uniform(0.001, 0.01, 2)) for _ in range(4)])
        groups.append((anchors, fixes, ranges, cov))
    var = rng.uniform(0.0005, 0.003, len(groups))
    stack = [np.stack([g[i] for g in groups]) for i in range(4)]
    got = check_mirror_2d(stack[0], stack[1], stack[2], var, stack[3] if with_cov else None, loss, 2.0)
    for k, (anchors, fixes, ranges, cov) in enumerate(groups):
        want = _reference_mirror(anchors, fixes, ranges, var[k], cov if with_cov else None, loss, 2.0)
        np.testing.assert_allclose(got[0][k], want[0], rtol=1e-9, atol=1e-12, equal_nan=True)
        np.testing.assert_array_equal(got[1][k], want[1])
        np.testing.assert_array_equal(got[2][k], want[2])
        outcomes |= set(want[1].tolist()) | ({"switched"} if want[2].any() else set())
    assert {0, 1, 2, "switched"} <= outcomes  # every branch exercised


@pytest.mark.parametrize("dim", [2, 3])
def test_residual_statistics_match_numpy(dim, rng):
    from uwb_env.localization._tracking_kernel import residual_statistics

    s, m, n = 4, 5, 6
    anchors = rng.uniform(0, 20, (s, n, dim))
    positions = rng.uniform(0, 20, (s, m, dim))
    ranges = np.linalg.norm(positions[:, :, None] - anchors[:, None], axis=-1) + rng.normal(0, 0.1, (s, m, n))
    ranges[0, 1, 2] = np.nan
    positions[1, 3] = np.nan
    positions[2] = np.nan  # a group without any fix
    tag_mean, anchor_mean, any_fix = residual_statistics(anchors, positions, ranges)
    res = np.linalg.norm(positions[:, :, None] - anchors[:, None], axis=-1) - ranges  # NaN where either is
    fixed = np.isfinite(positions).all(-1)
    sq = np.where(fixed[..., None] & np.isfinite(res), res * res, 0.0)
    rms = np.sqrt(sq.sum(-1) / np.maximum((fixed[..., None] & np.isfinite(res)).sum(-1), 1))
    for g in range(s):
        assert any_fix[g] == fixed[g].any()
        if fixed[g].any():
            np.testing.assert_allclose(tag_mean[g], rms[g][fixed[g]].mean(), rtol=1e-12)
            seen = np.isfinite(res[g]) & fixed[g][:, None]
            want = np.where(seen, np.abs(res[g]), 0.0).sum(0) / np.maximum(seen.sum(0), 1)
            np.testing.assert_allclose(anchor_mean[g], want, rtol=1e-12)
