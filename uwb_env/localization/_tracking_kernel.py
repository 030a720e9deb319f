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

TAG_OK, TAG_AMBIGUOUS, TAG_NO_FIX = 0, 1, 2


@njit(cache=True)
def _line_of_sight_terms(var, cov, use_cov, s, var0, kx, ky):
    """Per anchor of group s: sigma^2 + tr(C)/2 and the anisotropic part of u^T C u."""
    for k in range(len(var0)):
        if use_cov:
            c00, c01, c11 = cov[s, k, 0, 0], cov[s, k, 0, 1], cov[s, k, 1, 1]
            var0[k] = var[s] + 0.5 * (c00 + c11)
            kx[k] = 0.5 * (c00 - c11)
            ky[k] = c01
        else:
            var0[k] = var[s]
            kx[k] = 0.0
            ky[k] = 0.0


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
        r = ranges_row[k]
        if r != r:
            continue
        dx, dy = px - anchors[s, k, 0], py - anchors[s, k, 1]
        e = math.sqrt(dx * dx + dy * dy) - r
        total += e * e
        seen += 1
    return total / var, seen


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
        # principal axis of the anchors: e^{2i theta} = direction of sum (a - centre)^2
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
        sigma = math.sqrt(var[s])
        terms_ready = False
        for m in range(m_count):
            px, py = positions[s, m, 0], positions[s, m, 1]
            if not (math.isfinite(px) and math.isfinite(py)):
                status[s, m] = TAG_NO_FIX
                continue
            if n_count < 3:
                continue
            # mirror across the axis: centre + e^{2i theta} conj(p - centre)
            qx, qy = px - cx, -(py - cy)
            mx, my = cx + tx * qx - ty * qy, cy + tx * qy + ty * qx
            c_fix, n_valid = _chi2(anchors, s, ranges[s, m], px, py, var[s])
            c_raw, _ = _chi2(anchors, s, ranges[s, m], mx, my, var[s])
            # refining moves the mirror at most into the neighbouring minimum: only a raw misfit
            # within a generous bound can end within the margin
            if not (n_valid >= 3 and c_raw < c_fix + margin_chi2 + 50.0 * n_valid
                    and math.hypot(mx - px, my - py) > 3.0 * sigma):
                continue
            if not terms_ready:
                _line_of_sight_terms(var, cov, use_cov, s, var0, kx, ky)
                terms_ready = True
            rx, ry = _track_one(anchors, s, ranges[s, m], mx, my, var0, kx, ky, code, c, iterations)
            c_mir, _ = _chi2(anchors, s, ranges[s, m], rx, ry, var[s])
            if not (math.isfinite(c_mir) and math.hypot(rx - px, ry - py) > 3.0 * sigma):
                continue
            if c_mir < c_fix - margin_chi2:
                out[s, m, 0], out[s, m, 1] = rx, ry
                switched[s, m] = True
            elif abs(c_mir - c_fix) <= margin_chi2:
                status[s, m] = TAG_AMBIGUOUS
    return out, status, switched


@njit(cache=True)
def residual_statistics(anchors, positions, ranges):
    """Per group: the mean over fixed tags of their RMS range residual, each anchor's mean
    |residual| over the fixed tags that measured it, and whether any tag has a fix.
    anchors (S, N, D), positions (S, M, D) (NaN = no fix), ranges (S, M, N) (NaN = missing)."""
    s_count, m_count, n_count = ranges.shape
    dim = anchors.shape[2]
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
                d2 = 0.0
                for a in range(dim):
                    t = positions[s, m, a] - anchors[s, k, a]
                    d2 += t * t
                e = math.sqrt(d2) - r
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
