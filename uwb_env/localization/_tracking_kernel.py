"""Compiled planar Gauss-Newton tag tracking (numba): one loop for one env's handful of tags
and for thousands of copies alike (``multilateration.track_tags_2d`` documents the maths).

Why compiled: per tag and iteration the work is a few dozen flops over N anchors; in numpy the
batched env spent most of a step in array-call overhead of this kernel, and one env needed a
second, scalar Python copy of it to be fast for 3 tags.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from uwb_env.localization._lm_kernel import _weight


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
    kx = np.zeros(n_count)
    ky = np.zeros(n_count)
    for s in range(s_count):
        for k in range(n_count):
            if use_cov:
                c00, c01, c11 = cov[s, k, 0, 0], cov[s, k, 0, 1], cov[s, k, 1, 1]
                var0[k] = var[s] + 0.5 * (c00 + c11)
                kx[k] = 0.5 * (c00 - c11)
                ky[k] = c01
            else:
                var0[k] = var[s]
        for m in range(m_count):
            px, py = previous[s, m, 0], previous[s, m, 1]
            for _ in range(iterations):
                a11 = a12 = a22 = gx = gy = 0.0
                for k in range(n_count):
                    r = ranges[s, m, k]
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
