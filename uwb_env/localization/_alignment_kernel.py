"""Compiled 2D Procrustes and paper frame (numba).

Why compiled: the full solver aligns every candidate onto the prior and puts every start into
its gauge, a dozen times per later calibration of a few anchors; in numpy each is ~15 array
calls and an SVD of a 2 x 2 matrix (~70 us), for ~50 flops.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

FRAME_OK, FRAME_COINCIDENT, FRAME_COLLINEAR = 0, 1, 2


@njit(cache=True)
def _rotation_from_h(h00, h01, h10, h11, allow_reflection, rot):
    """The orthogonal 2 x 2 matrix maximizing trace(R^T H) into ``rot``: the rotation by the
    angle of (H00 + H11, H10 - H01), or (reflections allowed, det H < 0) the reflection
    [[cos f, sin f], [sin f, -cos f]] with f the angle of (H00 - H11, H01 + H10). A zero
    vector (singular H) gives the identity; a non-finite H a NaN matrix."""
    proper = not allow_reflection or h00 * h11 - h01 * h10 >= 0.0
    a = h00 + h11 if proper else h00 - h11
    b = h10 - h01 if proper else h01 + h10
    norm = math.hypot(a, b)
    c, s = (a / norm, b / norm) if norm > 0.0 else (1.0, 0.0)
    if not math.isfinite(h00 + h01 + h10 + h11):
        c = s = np.nan
    rot[0, 0], rot[1, 0] = c, s
    rot[0, 1], rot[1, 1] = (-s, c) if proper else (s, -c)


@njit(cache=True)
def rigid_align_2d(source, target, w, pivot, allow_reflection):
    """``alignment.rigid_align`` for (n, 2) points in closed form: with H the weighted
    cross-covariance, the rotation or reflection maximizing trace(R^T H)
    (``_rotation_from_h``; with reflections allowed the better of the two, by the sign of
    det H). Equal to the SVD's U V^T for a non-singular H; for a singular one (collinear points)
    both fit equally and the rotation is returned. (rot (2, 2), trans (2,))."""
    n = source.shape[0]
    if pivot >= 0:
        ms0, ms1 = source[pivot, 0], source[pivot, 1]
        mt0, mt1 = target[pivot, 0], target[pivot, 1]
    else:
        sw = ms0 = ms1 = mt0 = mt1 = 0.0
        for i in range(n):
            sw += w[i]
            ms0 += w[i] * source[i, 0]
            ms1 += w[i] * source[i, 1]
            mt0 += w[i] * target[i, 0]
            mt1 += w[i] * target[i, 1]
        ms0, ms1, mt0, mt1 = ms0 / sw, ms1 / sw, mt0 / sw, mt1 / sw
    h00 = h01 = h10 = h11 = 0.0
    for i in range(n):
        s0, s1 = source[i, 0] - ms0, source[i, 1] - ms1
        t0, t1 = w[i] * (target[i, 0] - mt0), w[i] * (target[i, 1] - mt1)
        h00 += t0 * s0
        h01 += t0 * s1
        h10 += t1 * s0
        h11 += t1 * s1
    rot = np.empty((2, 2))
    _rotation_from_h(h00, h01, h10, h11, bool(allow_reflection), rot)
    trans = np.empty(2)
    trans[0] = mt0 - (rot[0, 0] * ms0 + rot[0, 1] * ms1)
    trans[1] = mt1 - (rot[1, 0] * ms0 + rot[1, 1] * ms1)
    return rot, trans


@njit(cache=True)
def paper_frame_2d(points, origin, x_ref):
    """``alignment.paper_frame`` in 2D: (rot, trans, code); code FRAME_COINCIDENT when the
    reference anchors coincide, FRAME_COLLINEAR when every anchor lies on their line."""
    n = points.shape[0]
    o0, o1 = points[origin, 0], points[origin, 1]
    scale = 1e-12
    for i in range(n):
        scale = max(scale, abs(points[i, 0] - o0), abs(points[i, 1] - o1))
    rot = np.zeros((2, 2))
    trans = np.zeros(2)
    e0, e1 = points[x_ref, 0] - o0, points[x_ref, 1] - o1
    norm = math.sqrt(e0 * e0 + e1 * e1)
    if norm < 1e-9 * scale:
        return rot, trans, FRAME_COINCIDENT
    e0, e1 = e0 / norm, e1 / norm
    y0, y1 = -e1, e0
    total = 0.0
    far = 0.0
    for i in range(n):
        y = (points[i, 0] - o0) * y0 + (points[i, 1] - o1) * y1
        total += y
        far = max(far, abs(y))
    if far < 1e-6 * scale:
        return rot, trans, FRAME_COLLINEAR
    if total < 0.0:
        y0, y1 = -y0, -y1
    rot[0, 0], rot[0, 1], rot[1, 0], rot[1, 1] = e0, e1, y0, y1
    trans[0] = -(e0 * o0 + e1 * o1)
    trans[1] = -(y0 * o0 + y1 * o1)
    return rot, trans, FRAME_OK


@njit(cache=True)
def rigid_align_batch_2d(source, target):
    """``alignment.rigid_align_batch`` for (K, n, 2) point sets (unweighted, reflection allowed,
    no pivot): the same closed form per set, one loop instead of ~30 array calls (the batched
    env aligns a few candidates per poor-fit round). A non-finite set gives a NaN rotation."""
    k_sets, n = source.shape[0], source.shape[1]
    rot = np.empty((k_sets, 2, 2))
    trans = np.empty((k_sets, 2))
    for k in range(k_sets):
        ms0 = ms1 = mt0 = mt1 = 0.0
        for i in range(n):
            ms0 += source[k, i, 0]
            ms1 += source[k, i, 1]
            mt0 += target[k, i, 0]
            mt1 += target[k, i, 1]
        ms0, ms1, mt0, mt1 = ms0 / n, ms1 / n, mt0 / n, mt1 / n
        h00 = h01 = h10 = h11 = 0.0
        for i in range(n):
            s0, s1 = source[k, i, 0] - ms0, source[k, i, 1] - ms1
            t0, t1 = target[k, i, 0] - mt0, target[k, i, 1] - mt1
            h00 += t0 * s0
            h01 += t0 * s1
            h10 += t1 * s0
            h11 += t1 * s1
        _rotation_from_h(h00, h01, h10, h11, True, rot[k])
        trans[k, 0] = mt0 - (rot[k, 0, 0] * ms0 + rot[k, 0, 1] * ms1)
        trans[k, 1] = mt1 - (rot[k, 1, 0] * ms0 + rot[k, 1, 1] * ms1)
    return rot, trans
