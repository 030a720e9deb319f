"""Ground-truth errors of 2D teams, one compiled kernel for one env and for many copies.

Range-only calibration restores the constellation's shape, not where the frame has drifted or
turned (both unobservable from ranges). The paper measures positions relative to the anchors,
so the *constellation* errors are taken after the rigid transform (rotation + translation)
that best maps the true anchors onto their estimates: in 2D its rotation is e^{i theta} with
theta the angle of sum conj(a_k - mean a) (b_k - mean b) over true (a) and estimated (b)
anchors, the closed-form Procrustes solution. The *fixed* errors compare in the first
calibration's frame directly, and the rotation error is the angle between the true and
estimated directions anchor 0 -> anchor 1 (paper Fig. 5).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True)
def planar_errors(rot, origin, anchors_true, tags_true, anchors_est, tag_fix, cap, fixed=True):
    """rot (B, 2, 2), origin (B, 2): the world -> estimate frame map of each copy (estimate
    frame point = rot @ (world point - origin)); anchors_true (B, N, 2), tags_true (B, M, 2)
    in the world frame; anchors_est (B, N, 2), tag_fix (B, M, 2) (NaN = no fix).

    Returns anchor errors (B, N) and tag errors (B, M) after the constellation transform,
    the same in the fixed frame, and the rotation error (B,) in rad. Tag errors are capped at
    ``cap`` (a tag without a fix counts as ``cap``); anchor errors are not. ``fixed=False``
    (the batched env, which reads the constellation errors only): the fixed-frame errors and
    the rotation are not computed (empty arrays; half the kernel's square roots)."""
    b_count, n, _ = anchors_true.shape
    m = tags_true.shape[1]
    kept = b_count if fixed else 0
    a_const = np.empty((b_count, n))
    a_fixed = np.empty((kept, n))
    t_const = np.empty((b_count, m))
    t_fixed = np.empty((kept, m))
    rotation = np.empty(kept)
    ax = np.empty(n)
    ay = np.empty(n)
    for b in range(b_count):
        r00, r01, r10, r11 = rot[b, 0, 0], rot[b, 0, 1], rot[b, 1, 0], rot[b, 1, 1]
        ox, oy = origin[b, 0], origin[b, 1]
        msx = msy = mtx = mty = 0.0
        for k in range(n):
            x, y = anchors_true[b, k, 0] - ox, anchors_true[b, k, 1] - oy
            ax[k], ay[k] = r00 * x + r01 * y, r10 * x + r11 * y
            msx += ax[k]
            msy += ay[k]
            mtx += anchors_est[b, k, 0]
            mty += anchors_est[b, k, 1]
        msx /= n
        msy /= n
        mtx /= n
        mty /= n
        re = im = 0.0
        for k in range(n):  # sum conj(s) t
            sx, sy = ax[k] - msx, ay[k] - msy
            tx, ty = anchors_est[b, k, 0] - mtx, anchors_est[b, k, 1] - mty
            re += sx * tx + sy * ty
            im += sx * ty - sy * tx
        norm = math.hypot(re, im)
        cx, cy = (re / norm, im / norm) if norm > 0.0 else (1.0, 0.0)
        for k in range(n):
            sx, sy = ax[k] - msx, ay[k] - msy
            px, py = cx * sx - cy * sy + mtx, cx * sy + cy * sx + mty
            ex, ey = anchors_est[b, k, 0], anchors_est[b, k, 1]
            a_const[b, k] = math.hypot(ex - px, ey - py)
            if fixed:
                a_fixed[b, k] = math.hypot(ex - ax[k], ey - ay[k])
        for k in range(m):
            x, y = tags_true[b, k, 0] - ox, tags_true[b, k, 1] - oy
            tx, ty = r00 * x + r01 * y, r10 * x + r11 * y
            sx, sy = tx - msx, ty - msy
            px, py = cx * sx - cy * sy + mtx, cx * sy + cy * sx + mty
            ex, ey = tag_fix[b, k, 0], tag_fix[b, k, 1]
            e1 = math.hypot(ex - px, ey - py)
            t_const[b, k] = e1 if e1 <= cap else cap  # NaN (no fix) -> the cap
            if fixed:
                e2 = math.hypot(ex - tx, ey - ty)
                t_fixed[b, k] = e2 if e2 <= cap else cap
        if not fixed:
            continue
        # angle between true and estimated directions 0 -> 1
        dx, dy = ax[1] - ax[0], ay[1] - ay[0]
        fx, fy = anchors_est[b, 1, 0] - anchors_est[b, 0, 0], anchors_est[b, 1, 1] - anchors_est[b, 0, 1]
        rotation[b] = abs(math.atan2(dy * fx - dx * fy, dx * fx + dy * fy))
    return a_const, t_const, a_fixed, t_fixed, rotation
