"""Compiled planar tag tracking and mirror checks (numba): one loop for one env's handful of
tags and for thousands of copies alike (``multilateration.track_tags_2d`` and
``check_mirror_2d`` document the maths).

Why compiled: per tag and iteration the work is a few dozen flops over N anchors; in numpy the
batched env spent most of a step in array-call overhead of these kernels, and one env needed a
second, scalar Python copy of the tracker to be fast for 3 tags.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from uwb_env.localization._lm_kernel import _weight

TAG_OK, TAG_AMBIGUOUS, TAG_NO_FIX, TAG_POOR_FIT = 0, 1, 2, 3


@njit(cache=True)
def _set_terms(k, v, c00, c01, c11, var0, kx, ky):
    """Anchor k's sigma^2 + tr(C)/2 and the anisotropic part of u^T C u, for range variance v
    and anchor covariance [[c00, c01], [c01, c11]]."""
    var0[k] = v + 0.5 * (c00 + c11)
    kx[k] = 0.5 * (c00 - c11)
    ky[k] = c01


@njit(cache=True)
def _line_of_sight_terms(var, cov, use_cov, s, var0, kx, ky):
    """Per anchor of group s: sigma^2 + tr(C)/2 and the anisotropic part of u^T C u."""
    for k in range(len(var0)):
        if use_cov:
            _set_terms(k, var[s], cov[s, k, 0, 0], cov[s, k, 0, 1], cov[s, k, 1, 1], var0, kx, ky)
        else:
            _set_terms(k, var[s], 0.0, 0.0, 0.0, var0, kx, ky)


@njit(cache=True)
def _track_one(anchors, s, ranges_row, px, py, var0, kx, ky, code, c, iterations):
    """Gauss-Newton steps of one tag against group s's anchors; returns the new (px, py)."""
    for _ in range(iterations):
        a11 = a12 = a22 = gx = gy = 0.0
        for k in range(len(ranges_row)):
            r = ranges_row[k]
            if r != r:  # missing range
                continue
            dx, dy = px - anchors[s, k, 0], py - anchors[s, k, 1]
            dist = max(math.sqrt(dx * dx + dy * dy), 1e-12)
            ux, uy = dx / dist, dy / dist
            res = dist - r
            # 1 / (sigma^2 + u^T C u): the anchor's uncertainty along the line of sight
            w = 1.0 / (var0[k] + kx[k] * (ux * ux - uy * uy) + 2.0 * ky[k] * ux * uy)
            if code != 0:
                w *= _weight(res * math.sqrt(w), code, c)
            wx, wy = w * ux, w * uy
            a11 += wx * ux
            a12 += wx * uy
            a22 += wy * uy
            gx += wx * res
            gy += wy * res
        det = a11 * a22 - a12 * a12
        if det > 1e-300:  # otherwise (no two independent directions) the tag keeps its place
            px, py = px - (a22 * gx - a12 * gy) / det, py - (a11 * gy - a12 * gx) / det
    return px, py


@njit(cache=True)
def track_2d(anchors, previous, ranges, var, cov, use_cov, code, c, iterations):
    """anchors (S, N, 2), previous (S, M, 2), ranges (S, M, N) NaN = missing, var (S,) range
    variance per group, cov (S, N, 2, 2) read only if ``use_cov``; robust ``code``/``c`` as
    ``_lm_kernel``. Returns positions (S, M, 2), rms (S, M), residuals (S, M, N): NaN for a
    tag with fewer than 3 ranges or a non-finite fix (residuals also where a range is missing)."""
    s_count, m_count, n_count = ranges.shape
    pos = np.empty((s_count, m_count, 2))
    rms = np.empty((s_count, m_count))
    res_out = np.empty((s_count, m_count, n_count))
    var0 = np.empty(n_count)
    kx = np.empty(n_count)
    ky = np.empty(n_count)
    for s in range(s_count):
        _line_of_sight_terms(var, cov, use_cov, s, var0, kx, ky)
        for m in range(m_count):
            px, py = _track_one(anchors, s, ranges[s, m], previous[s, m, 0], previous[s, m, 1], var0, kx, ky, code,
                                c, iterations)
            total = 0.0
            seen = 0
            for k in range(n_count):
                r = ranges[s, m, k]
                if r != r:
                    res_out[s, m, k] = np.nan
                    continue
                dx, dy = px - anchors[s, k, 0], py - anchors[s, k, 1]
                e = math.sqrt(dx * dx + dy * dy) - r
                res_out[s, m, k] = e
                total += e * e
                seen += 1
            err = math.sqrt(total / seen) if seen else np.nan
            if seen < 3 or not math.isfinite(err):
                px = py = err = np.nan
                for k in range(n_count):
                    res_out[s, m, k] = np.nan
            pos[s, m, 0], pos[s, m, 1] = px, py
            rms[s, m] = err
    return pos, rms, res_out


@njit(cache=True)
def _chi2(anchors, s, ranges_row, px, py, var):
    """Sum of squared range residuals over the measured ranges / var, and their count."""
    total = 0.0
    seen = 0
    for k in range(len(ranges_row)):
        e = _range_residual(anchors, s, k, ranges_row[k], px, py)
        if e == e:  # a missing range gives NaN
            total += e * e
            seen += 1
    return total / var, seen


@njit(cache=True)
def _range_residual(anchors, s, k, r, px, py):
    """Fitted minus measured range to anchor k of group s (NaN where the range is missing)."""
    dx, dy = px - anchors[s, k, 0], py - anchors[s, k, 1]
    return math.sqrt(dx * dx + dy * dy) - r


@njit(cache=True)
def _mirror_axis(anchors, s):
    """Centre and e^{2i theta} (theta the principal axis' angle) of group s's anchors: the mirror
    of p is centre + e^{2i theta} conj(p - centre)."""
    n_count = anchors.shape[1]
    cx = cy = 0.0
    for k in range(n_count):
        cx += anchors[s, k, 0]
        cy += anchors[s, k, 1]
    cx /= n_count
    cy /= n_count
    sxx = sxy = 0.0
    for k in range(n_count):
        dx, dy = anchors[s, k, 0] - cx, anchors[s, k, 1] - cy
        sxx += dx * dx - dy * dy
        sxy += 2.0 * dx * dy
    norm = math.sqrt(sxx * sxx + sxy * sxy)
    tx, ty = (sxx / norm, sxy / norm) if norm > 0.0 else (1.0, 0.0)
    return cx, cy, tx, ty


@njit(cache=True)
def _mirror_candidate(anchors, s, row, px, py, axis, var, margin_chi2):
    """The raw mirror of a finite fix and whether it deserves a refinement: enough ranges, a
    raw misfit within a generous bound (refining moves it at most into the neighbouring
    minimum) and clearly apart (3 range stds). Returns (candidate, mx, my, chi2 of the fix)."""
    c_fix, n_valid = _chi2(anchors, s, row, px, py, var)
    return _mirror_candidate_given(anchors, s, row, px, py, axis, var, margin_chi2, c_fix, n_valid)


@njit(cache=True)
def _mirror_candidate_given(anchors, s, row, px, py, axis, var, margin_chi2, c_fix, n_valid):
    """``_mirror_candidate`` with the fix's chi-square and range count already known."""
    cx, cy, tx, ty = axis
    qx, qy = px - cx, -(py - cy)
    mx, my = cx + tx * qx - ty * qy, cy + tx * qy + ty * qx
    c_raw, _ = _chi2(anchors, s, row, mx, my, var)
    ok = (n_valid >= 3 and c_raw < c_fix + margin_chi2 + 50.0 * n_valid
          and math.hypot(mx - px, my - py) > 3.0 * math.sqrt(var))
    return ok, mx, my, c_fix


@njit(cache=True)
def _mirror_verdict(anchors, s, row, px, py, rx, ry, c_fix, var, margin_chi2):
    """After refining the mirror to (rx, ry): 1 switch (the ranges reject the fix for it),
    2 ambiguous (both fit within the margin, clearly apart), 0 keep."""
    c_mir, _ = _chi2(anchors, s, row, rx, ry, var)
    if not (math.isfinite(c_mir) and math.hypot(rx - px, ry - py) > 3.0 * math.sqrt(var)):
        return 0
    if c_mir < c_fix - margin_chi2:
        return 1
    if abs(c_mir - c_fix) <= margin_chi2:
        return 2
    return 0


@njit(cache=True)
def mirror_check_2d(anchors, positions, ranges, var, cov, use_cov, code, c, margin_chi2, iterations):
    """The mirror check of ``multilateration.check_mirror_2d`` for every tag of every group.
    Returns (positions, status int8, switched bool)."""
    s_count, m_count, n_count = ranges.shape
    out = positions.copy()
    status = np.zeros((s_count, m_count), np.int8)
    switched = np.zeros((s_count, m_count), np.bool_)
    var0 = np.empty(n_count)
    kx = np.empty(n_count)
    ky = np.empty(n_count)
    for s in range(s_count):
        axis = _mirror_axis(anchors, s)
        terms_ready = False
        for m in range(m_count):
            px, py = positions[s, m, 0], positions[s, m, 1]
            if not (math.isfinite(px) and math.isfinite(py)):
                status[s, m] = TAG_NO_FIX
                continue
            if n_count < 3:
                continue
            ok, mx, my, c_fix = _mirror_candidate(anchors, s, ranges[s, m], px, py, axis, var[s], margin_chi2)
            if not ok:
                continue
            if not terms_ready:
                _line_of_sight_terms(var, cov, use_cov, s, var0, kx, ky)
                terms_ready = True
            rx, ry = _track_one(anchors, s, ranges[s, m], mx, my, var0, kx, ky, code, c, iterations)
            verdict = _mirror_verdict(anchors, s, ranges[s, m], px, py, rx, ry, c_fix, var[s], margin_chi2)
            if verdict == 1:
                out[s, m, 0], out[s, m, 1] = rx, ry
                switched[s, m] = True
            elif verdict == 2:
                status[s, m] = TAG_AMBIGUOUS
    return out, status, switched


@njit(cache=True)
def residual_statistics(anchors, positions, ranges):
    """Per group: the mean over fixed tags of their RMS range residual, each anchor's mean
    |residual| over the fixed tags that measured it, and whether any tag has a fix.
    anchors (S, N, D), positions (S, M, D) (NaN = no fix), ranges (S, M, N) (NaN = missing)."""
    s_count, m_count, n_count = ranges.shape
    dim = anchors.shape[2]
    res = np.empty((s_count, m_count, n_count))
    for s in range(s_count):
        for m in range(m_count):
            for k in range(n_count):
                d2 = 0.0
                for a in range(dim):
                    t = positions[s, m, a] - anchors[s, k, a]
                    d2 += t * t
                res[s, m, k] = math.sqrt(d2) - ranges[s, m, k]
    return statistics_of_residuals(positions, ranges, res)


@njit(cache=True)
def statistics_of_residuals(positions, ranges, res):
    """``residual_statistics`` from the fitted-minus-measured ranges ``res`` (S, M, N) of the
    fixes ``positions`` (read only where a fix is finite and its range measured)."""
    s_count, m_count, n_count = ranges.shape
    dim = positions.shape[2]
    tag_mean = np.zeros(s_count)
    anchor_mean = np.zeros((s_count, n_count))
    any_fix = np.zeros(s_count, np.bool_)
    count = np.zeros(n_count)
    for s in range(s_count):
        fixed = 0
        count[:] = 0.0
        for m in range(m_count):
            finite = True
            for a in range(dim):
                finite &= math.isfinite(positions[s, m, a])
            if not finite:
                continue
            total = 0.0
            seen = 0
            for k in range(n_count):
                r = ranges[s, m, k]
                if r != r:
                    continue
                e = res[s, m, k]
                total += e * e
                seen += 1
                anchor_mean[s, k] += abs(e)
                count[k] += 1.0
            if seen:
                tag_mean[s] += math.sqrt(total / seen)
                fixed += 1
        if fixed:
            tag_mean[s] /= fixed
            any_fix[s] = True
        for k in range(n_count):
            anchor_mean[s, k] /= max(count[k], 1.0)
    return tag_mean, anchor_mean, any_fix


@njit(cache=True)
def _drift_terms(anchor_cov, pred_var, cal_var, use_cov, s, v, var0, kx, ky):
    """``_line_of_sight_terms`` of group s with range variance v and each anchor's covariance
    its calibration's plus the isotropic drift part (pred_var - cal_var) / 2 per axis."""
    for k in range(len(var0)):
        if use_cov:
            d = (pred_var[s, k] - cal_var[s, k]) / 2.0
            _set_terms(k, v, anchor_cov[s, k, 0, 0] + d, anchor_cov[s, k, 0, 1] + 0.0, anchor_cov[s, k, 1, 1] + d,
                       var0, kx, ky)
        else:
            _set_terms(k, v, 0.0, 0.0, 0.0, var0, kx, ky)


@njit(cache=True)
def _residual_row(anchors, s, ranges_row, px, py, out):
    """Fitted minus measured range to every anchor of group s into ``out`` (NaN where a range is
    missing); returns the sum of squares over the measured ones and their count (``_chi2``'s
    sum, in the same order)."""
    total = 0.0
    seen = 0
    for k in range(len(ranges_row)):
        e = _range_residual(anchors, s, k, ranges_row[k], px, py)
        out[k] = e
        if e == e:
            total += e * e
            seen += 1
    return total, seen


@njit(cache=True)
def _rms_from(total, seen):
    """RMS range residual from a residual row's sum of squares and count; NaN below 3 ranges or
    when not finite (the tracker's rule)."""
    err = math.sqrt(total / seen) if seen else np.nan
    if seen < 3 or not math.isfinite(err):
        return np.nan
    return err


@njit(cache=True)
def _closed_form(anchors, s, ranges_row, var):
    """Weighted linear least squares in (x, y, |p|^2): a range r to anchor a gives
    -2 a.p + |p|^2 = r^2 - |a|^2, weight 1 / var(r^2) = 1 / (4 r^2 var + 2 var^2) (the second
    term keeps a range of ~0 m from weighing ~1e12). Returns (ok, x, y); not ok below 3 ranges
    or for a singular system."""
    n00 = n01 = n02 = n11 = n12 = n22 = 0.0
    b0 = b1 = b2 = 0.0
    seen = 0
    for k in range(len(ranges_row)):
        r = ranges_row[k]
        if r != r:
            continue
        seen += 1
        ax, ay = anchors[s, k, 0], anchors[s, k, 1]
        w = 1.0 / (4.0 * r * r * var + 2.0 * var * var)  # 1 / var(r^2) for Gaussian range noise
        d0, d1 = -2.0 * ax, -2.0 * ay
        rhs = r * r - (ax * ax + ay * ay)
        n00 += w * d0 * d0
        n01 += w * d0 * d1
        n02 += w * d0
        n11 += w * d1 * d1
        n12 += w * d1
        n22 += w
        b0 += w * d0 * rhs
        b1 += w * d1 * rhs
        b2 += w * rhs
    if seen < 3:
        return False, np.nan, np.nan
    # LU with partial pivoting (as LAPACK's gesv), not Cramer's rule: the system can be badly
    # conditioned (anchors far from the origin, near-collinear anchors)
    a = np.array([[n00 + 1e-12, n01, n02, b0], [n01, n11 + 1e-12, n12, b1], [n02, n12, n22 + 1e-12, b2]])
    for col in range(3):
        piv = col
        for r in range(col + 1, 3):
            if abs(a[r, col]) > abs(a[piv, col]):
                piv = r
        if not (math.isfinite(a[piv, col]) and a[piv, col] != 0.0):
            return False, np.nan, np.nan
        if piv != col:
            for q in range(4):
                a[col, q], a[piv, q] = a[piv, q], a[col, q]
        for r in range(col + 1, 3):
            f = a[r, col] / a[col, col]
            for q in range(col, 4):
                a[r, q] -= f * a[col, q]
    z = a[2, 3] / a[2, 2]
    y = (a[1, 3] - a[1, 2] * z) / a[1, 1]
    x = (a[0, 3] - a[0, 1] * y - a[0, 2] * z) / a[0, 0]
    return math.isfinite(x) and math.isfinite(y), x, y


@njit(cache=True)
def _degenerate(anchors, s, ranges_row, px, py):
    """The ranges do not fix (px, py) in two directions (``multilateration``'s DEGENERATE rule:
    smallest eigenvalue of sum u u^T at most 1e-8 of the largest), e.g. collinear anchors."""
    a11 = a12 = a22 = 0.0
    for k in range(len(ranges_row)):
        if ranges_row[k] != ranges_row[k]:
            continue
        dx, dy = px - anchors[s, k, 0], py - anchors[s, k, 1]
        dist = max(math.sqrt(dx * dx + dy * dy), 1e-12)
        ux, uy = dx / dist, dy / dist
        a11 += ux * ux
        a12 += ux * uy
        a22 += uy * uy
    half = 0.5 * (a11 + a22)
    root = math.sqrt(max(half * half - (a11 * a22 - a12 * a12), 0.0))
    return not half - root > 1e-8 * (half + root)


@njit(cache=True)
def _poor_fit(pred_var, s, residuals, v, fit_chi2):
    """Whether the ranges reject a fix (its residual row, NaN = missing range) at the fit
    test's level: their chi-square with each range's variance v + pred_var / 2 above
    fit_chi2[measured ranges - 2]."""
    total = 0.0
    seen = 0
    for k in range(len(residuals)):
        e = residuals[k]
        if e == e:
            total += e * e / (v + 0.5 * pred_var[s, k])
            seen += 1
    return seen >= 3 and total > fit_chi2[seen - 2]


@njit(cache=True)
def tag_step_2d(anchors, previous, ranges, range_var, pred_var, cal_var, anchor_cov, use_cov, code, c, iterations,
                restart_base_m, refit_iterations, margin_chi2, mirror_iterations, fit_chi2):
    """One step of tag fixing for every tag of every group (both envs: ``multilateration.fix_tags_2d``).

    anchors (S, N, 2) estimates; previous (S, M, 2) last fixes (NaN = none); ranges (S, M, N)
    (NaN = missing); range_var (S,) one range's variance; pred_var / cal_var (S, N) each
    anchor's predicted / calibration error variance; anchor_cov (S, N, 2, 2) its calibration
    covariance (read if ``use_cov``). Per tag: ``iterations`` Gauss-Newton steps from its last
    fix; no fix, or an RMS residual above restart_base_m + 2 sqrt(max pred_var), gets the
    closed form refined by ``refit_iterations`` steps, kept if its residual is lower; then the
    mirror check (range variance + mean(pred_var) / 2); then the fit test: a fix that is not
    ambiguous but whose ranges' chi-square (each range's variance: range_var + pred_var / 2,
    the anchor's predicted error along any line of sight) exceeds fit_chi2[measured - 2] is
    TAG_POOR_FIT (ranges its anchors cannot explain); then the residual statistics.

    Returns positions (S, M, 2), rms (S, M) (NaN = no fix), status (S, M) int8, switched and
    refit (S, M) bool, tag_mean (S,), anchor_mean (S, N), any_fix (S,)."""
    s_count, m_count, n_count = ranges.shape
    pos = np.empty((s_count, m_count, 2))
    rms = np.empty((s_count, m_count))
    status = np.zeros((s_count, m_count), np.int8)
    switched = np.zeros((s_count, m_count), np.bool_)
    refit = np.zeros((s_count, m_count), np.bool_)
    var0 = np.empty(n_count)
    kx = np.empty(n_count)
    ky = np.empty(n_count)
    mvar0 = np.empty(n_count)
    mkx = np.empty(n_count)
    mky = np.empty(n_count)
    # each tag's residual row at its fix, computed once: the fit test, the mirror check's chi-square
    # of the fix and the residual statistics read it (they each recomputed it before)
    res = np.full((s_count, m_count, n_count), np.nan)
    cand = np.empty(n_count)
    for s in range(s_count):
        v = range_var[s]
        _drift_terms(anchor_cov, pred_var, cal_var, use_cov, s, v, var0, kx, ky)
        top = 0.0
        total_pred = 0.0
        for k in range(n_count):
            top = max(top, pred_var[s, k])
            total_pred += pred_var[s, k]
        # stale anchors raise every residual; only more than they explain means a wrong minimum
        restart = restart_base_m + 2.0 * math.sqrt(top)
        mvar = v + total_pred / n_count / 2
        axis = _mirror_axis(anchors, s)
        mirror_terms = False
        for m in range(m_count):
            row = ranges[s, m]
            here = res[s, m]
            px, py = previous[s, m, 0], previous[s, m, 1]
            err = np.nan
            total, seen = 0.0, 0
            if math.isfinite(px) and math.isfinite(py):
                px, py = _track_one(anchors, s, row, px, py, var0, kx, ky, code, c, iterations)
                total, seen = _residual_row(anchors, s, row, px, py, here)
                err = _rms_from(total, seen)
            if not err <= restart:
                ok, sx, sy = _closed_form(anchors, s, row, v)
                if ok:
                    qx, qy = _track_one(anchors, s, row, sx, sy, var0, kx, ky, code, c, refit_iterations)
                    total2, seen2 = _residual_row(anchors, s, row, qx, qy, cand)
                    e2 = _rms_from(total2, seen2)
                    if math.isfinite(e2) and not e2 >= err and not _degenerate(anchors, s, row, qx, qy):
                        px, py, err, total, seen = qx, qy, e2, total2, seen2
                        here[:] = cand
                        refit[s, m] = True
            if not math.isfinite(err):
                pos[s, m, 0] = pos[s, m, 1] = np.nan
                rms[s, m] = np.nan
                status[s, m] = TAG_NO_FIX
                continue
            if n_count >= 3:
                ok, mx, my, c_fix = _mirror_candidate_given(anchors, s, row, px, py, axis, mvar, margin_chi2,
                                                            total / mvar, seen)
                if ok:
                    if not mirror_terms:
                        _drift_terms(anchor_cov, pred_var, cal_var, use_cov, s, mvar, mvar0, mkx, mky)
                        mirror_terms = True
                    rx, ry = _track_one(anchors, s, row, mx, my, mvar0, mkx, mky, code, c, mirror_iterations)
                    verdict = _mirror_verdict(anchors, s, row, px, py, rx, ry, c_fix, mvar, margin_chi2)
                    if verdict == 1:
                        px, py = rx, ry
                        switched[s, m] = True
                        e2 = _rms_from(*_residual_row(anchors, s, row, px, py, here))
                        err = e2 if math.isfinite(e2) else err
                    elif verdict == 2:
                        status[s, m] = TAG_AMBIGUOUS
            if status[s, m] == TAG_OK and _poor_fit(pred_var, s, here, v, fit_chi2):
                status[s, m] = TAG_POOR_FIT
            pos[s, m, 0], pos[s, m, 1] = px, py
            rms[s, m] = err
    tag_mean, anchor_mean, any_fix = statistics_of_residuals(pos, ranges, res)
    return pos, rms, status, switched, refit, tag_mean, anchor_mean, any_fix
