"""Rigid alignment (Procrustes) and the paper's frame convention."""

from __future__ import annotations

import numpy as np

from uwb_env.localization._alignment_kernel import (
    FRAME_COINCIDENT,
    FRAME_OK,
    paper_frame_2d,
    rigid_align_2d,
    rigid_align_batch_2d,
)
from uwb_env.localization.errors import GeometryError


def rigid_align(
    source: np.ndarray,
    target: np.ndarray,
    weights: np.ndarray | None = None,
    allow_reflection: bool = True,
    pivot: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Best orthogonal transform with ``target ~= source @ R.T + t`` (weighted Kabsch).

    Args:
        source, target: (n, dim) point sets.
        weights: optional (n,) non-negative weights.
        allow_reflection: if False, R is a proper rotation (det +1).
        pivot: if given, the transform maps ``source[pivot]`` exactly onto ``target[pivot]``
            (rotation about that point), as used for "anchor 0 stays where it is".

    Returns:
        (R (dim, dim), t (dim,)). In 2D in closed form (``_alignment_kernel.rigid_align_2d``:
        the SVD's answer for a non-singular cross-covariance, a rotation for a singular one).
    """
    source = np.asarray(source, dtype=float)
    target = np.asarray(target, dtype=float)
    w = np.ones(len(source)) if weights is None else np.asarray(weights, dtype=float)
    n = len(source)
    if pivot is not None and not -n <= int(pivot) < n:
        raise IndexError(f"pivot={pivot!r}: out of range for {n} points")
    if source.ndim == 2 and source.shape[1] == 2 and target.shape == source.shape and w.shape == (n,) \
            and n > 0 and w.sum() > 0:
        rot, trans = rigid_align_2d(source, target, w, -1 if pivot is None else int(pivot) % n, bool(allow_reflection))
        if np.isfinite(rot).all() and np.isfinite(trans).all():
            return rot, trans
        # non-finite points: numpy's error, as before
    if pivot is None:
        mu_s = (w[:, None] * source).sum(0) / w.sum()
        mu_t = (w[:, None] * target).sum(0) / w.sum()
    else:
        mu_s, mu_t = source[pivot], target[pivot]
    cov = ((target - mu_t) * w[:, None]).T @ (source - mu_s)
    u, _, vt = np.linalg.svd(cov)
    d = np.ones(source.shape[1])
    if not allow_reflection and np.linalg.det(u @ vt) < 0:
        d[-1] = -1.0
    rot = (u * d) @ vt
    return rot, mu_t - mu_s @ rot.T


def apply(rot: np.ndarray, trans: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ rot.T + trans


def aligned_errors(estimate: np.ndarray, truth: np.ndarray, allow_reflection: bool = True) -> np.ndarray:
    """Per-point error after the best rigid alignment of ``estimate`` onto ``truth``."""
    rot, trans = rigid_align(estimate, truth, allow_reflection=allow_reflection)
    return np.linalg.norm(apply(rot, trans, estimate) - truth, axis=1)


def frame_refs(points: np.ndarray, origin: int = 0, x_ref: int = 1) -> tuple[int, ...]:
    """Anchors fixing the frame: (origin, x_ref) in 2D; plus the anchor farthest off the x
    axis in 3D (it fixes the rotation about x). Raises GeometryError when degenerate."""
    points = np.asarray(points, dtype=float)
    rel = points - points[origin]
    scale = max(np.abs(rel).max(), 1e-12)
    ex = rel[x_ref]
    if np.linalg.norm(ex) < 1e-9 * scale:
        raise GeometryError(f"anchors {origin} and {x_ref} coincide: the x axis is undefined")
    ex = ex / np.linalg.norm(ex)
    off = np.linalg.norm(rel - np.outer(rel @ ex, ex), axis=1)
    if off.max() < 1e-6 * scale:
        raise GeometryError("all anchors are collinear: the frame cannot be fixed")
    if points.shape[1] == 2:
        return (origin, x_ref)
    return (origin, x_ref, int(np.argmax(off)))


def rigid_align_batch(source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`rigid_align` (unweighted, reflection allowed, no pivot) for (K, n, dim) point sets
    at once: (R (K, dim, dim), t (K, dim)) with ``target ~= source @ R.T + t``.

    In 2D the orthogonal Procrustes solution in closed form: with H the cross-covariance, the
    rotation by atan2(H10 - H01, H00 + H11) where det H >= 0, else the reflection
    [[cos f, sin f], [sin f, -cos f]] with f = atan2(H01 + H10, H00 - H11) (its mirror line at
    f / 2). For a non-singular H that is the SVD's U V^T; for a singular one (collinear or
    coincident points) a rotation and a reflection fit equally well and this picks the rotation.
    A batched SVD of 2 x 2 matrices costs ~5x more (one LAPACK call each). Non-finite points give
    a NaN rotation. In 3D a batched SVD."""
    if source.shape[2] == 2 and source.shape[1] > 0:  # compiled: one loop for all sets
        return rigid_align_batch_2d(np.ascontiguousarray(source, dtype=np.float64),
                                    np.ascontiguousarray(target, dtype=np.float64))
    mu_s, mu_t = source.mean(1), target.mean(1)
    u, _, vt = np.linalg.svd(np.einsum("kni,knj->kij", target - mu_t[:, None], source - mu_s[:, None]))
    rot = u @ vt
    return rot, mu_t - np.einsum("kij,kj->ki", rot, mu_s)


def paper_frame(points: np.ndarray, refs: tuple[int, ...] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The paper's frame: refs[0] at the origin, refs[1] on +x, the rest in +y.

    "The rest in +y" cannot hold for every deployment, so it fixes the reflection: the y axis
    points to the side where the other anchors' y coordinates sum positive. In 3D refs[2] (by
    default the anchor farthest off the x axis) lies in the xy-plane with y > 0 and the z
    axis points to the side where the other anchors' z sum positive (a right- or left-handed
    frame accordingly: ranges cannot tell mirror images apart).

    Returns (R, t) with ``frame_points = points @ R.T + t``.
    Raises GeometryError if the reference anchors coincide or all anchors are collinear
    (coplanar in 3D).
    """
    points = np.asarray(points, dtype=float)
    dim = points.shape[1]
    refs = frame_refs(points) if refs is None else refs
    if dim == 2 and np.isfinite(points).all() and all(-len(points) <= int(r) < len(points) for r in refs[:2]):
        rot, trans, code = paper_frame_2d(points, int(refs[0]) % len(points), int(refs[1]) % len(points))
        if code == FRAME_OK:
            return rot, trans
        if code == FRAME_COINCIDENT:
            raise GeometryError(f"anchors {refs[0]} and {refs[1]} coincide: the x axis is undefined")
        raise GeometryError("all anchors are collinear: the y axis is undefined")
    origin = points[refs[0]]
    rel = points - origin
    scale = max(np.abs(rel).max(), 1e-12)
    ex = rel[refs[1]]
    if np.linalg.norm(ex) < 1e-9 * scale:
        raise GeometryError(f"anchors {refs[0]} and {refs[1]} coincide: the x axis is undefined")
    ex = ex / np.linalg.norm(ex)
    if dim == 2:
        ey = np.array([-ex[1], ex[0]])
        y = rel @ ey
        if np.abs(y).max() < 1e-6 * scale:
            raise GeometryError("all anchors are collinear: the y axis is undefined")
        if y.sum() < 0:
            ey = -ey
        rot = np.stack([ex, ey])
        return rot, -rot @ origin
    v = rel[refs[2]]
    ey = v - (v @ ex) * ex
    if np.linalg.norm(ey) < 1e-6 * scale:
        raise GeometryError(f"anchors {refs[:3]} are collinear: the y axis is undefined")
    ey = ey / np.linalg.norm(ey)
    ez = np.cross(ex, ey)
    z = rel @ ez
    if np.abs(z).max() < 1e-6 * scale:
        raise GeometryError("all anchors are coplanar: a 3D frame cannot be fixed")
    if z.sum() < 0:
        ez = -ez
    rot = np.stack([ex, ey, ez])
    return rot, -rot @ origin
