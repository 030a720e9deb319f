"""Uncertainty of a least-squares shape that the ranges fix only beyond first order.

Three anchors whose averaged ranges do not close a triangle (collinear within the noise: a
thin strip, or a robot that drove onto the line of two others) have their least-squares
optimum on the line. The third anchor's offset from the line then changes every range only
quadratically: the information J^T W J has a null direction and no inverse, yet the answer is
the best fit and the data do bound the offset (the chi-square rises with its fourth power).
Raising on such a round threw away an estimate within a few Cramer-Rao bounds of the truth
(thin 3-anchor layouts: 7 % of first calibrations raised, their fits 0.1-4.4x the bound).

Along each such direction this module follows the *profile* chi-square (every other free
coordinate re-fitted by Gauss-Newton) to the points on either side where it has risen by one,
the one-sigma likelihood interval, and adds the profile optimum's displacement to those two
points as sigma points (the re-fitted coordinates move with it: lifting the third anchor off
the line shortens its ranges' projections). The well-determined directions keep the inverse
information. The profile, not the slice (the other coordinates held): holding them would make
the interval too narrow.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import minimize_scalar

from uwb_env.localization.errors import GeometryError

# An eigenvalue of the information below this fraction of the largest: a direction the ranges
# fix only beyond first order (the solver refuses its inverse at a reciprocal condition 1e-10).
NULL_REL = 1e-9
BISECTIONS = 12  # half-width to 2^-12 of its bracket
GAUSS_NEWTON_ITERATIONS = 8


def degenerate_fit(positions: np.ndarray, free: np.ndarray, information: np.ndarray, pairs: np.ndarray,
                   dist: np.ndarray, weights: np.ndarray, max_null: int) -> tuple[np.ndarray, np.ndarray, int]:
    """The fit polished in the well-determined directions, its (n*dim, n*dim) covariance and
    the number of null directions.

    The solver stops an iteration-capped crawl towards the line (Newton steps along a quartic
    direction shrink geometrically), up to metres short of the optimum, with the other
    coordinates off theirs too: the fit is moved to the profile's minimum first
    (:func:`_profile_minimum`).

    Args:
        free: (n*dim,) mask of the estimated coordinates (the gauge's are fixed: zero rows).
        information: (F, F) J^T W J over the free coordinates at ``positions``.
        pairs, dist, weights: (P, 2) pairs, their ranges and 1/sigma^2 (the solve's weights).
        max_null: more null directions than this raise: the shape is not fixed (coplanar
            teams in 3D have one per anchor; the caller has other means there).

    Raises:
        GeometryError: too many null directions, or the chi-square does not rise by one along
            one of them within the scene's size (a flex: the ranges do not bound it).
    """
    n_coords = free.size
    scale = float(np.max(dist)) if len(dist) else 1.0
    lam, vec = np.linalg.eigh(information)
    # Null: below the solver's conditioning, or a quadratic variance beyond the scene's size
    # (where the quadratic model says nothing: an offset from the line of 300 m for anchors 5 m
    # apart). The least-determined direction always: the caller found the shape degenerate.
    null = (lam <= NULL_REL * max(float(lam[-1]), 0.0)) | (lam * scale * scale <= 1.0)
    null[0] = True
    k = int(null.sum())
    if k > max_null:
        raise GeometryError(f"degenerate anchor geometry: {k} directions the ranges do not fix "
                            f"(at most {max_null} are bounded from second order)")
    cov_free = (vec[:, ~null] / lam[~null]) @ vec[:, ~null].T
    x0 = positions.ravel()[free]
    for v in vec[:, null].T:
        x0 = _profile_minimum(positions, free, x0, vec[:, null], v, pairs, dist, weights, scale)
    flat = positions.ravel().copy()
    flat[free] = x0
    positions = flat.reshape(positions.shape)
    for v in vec[:, null].T:
        # The profile's path at the two one-sigma points, as sigma points: moving along v
        # drags the other coordinates (a third anchor lifted off the line shortens its range
        # projections), and that coupling is second order too, invisible to the information.
        for step in _profile_sigma_points(positions, free, x0, v, pairs, dist, weights, scale):
            cov_free += 0.5 * np.outer(step, step)
    cov = np.zeros((n_coords, n_coords))
    cov[np.ix_(free, free)] = cov_free
    return positions, cov, k


def shape_beyond_scene(positions: np.ndarray, pairs: np.ndarray, dist: np.ndarray, weights: np.ndarray) -> bool:
    """The shape's least-determined direction (the information over all coordinates, its
    dim(dim+1)/2 rigid-motion eigenvalues dropped: not the frame's) has a linearized variance
    beyond the scene's size squared: there the ranges fix it only to second order."""
    if len(pairs) == 0:
        return False
    dim = positions.shape[1]
    every = np.ones(positions.size, dtype=bool)
    _, _, jac = _chi2_and_jacobian(positions, every, positions.ravel(), pairs, dist, weights)
    shape_min = np.linalg.eigvalsh(jac.T @ jac)[dim * (dim + 1) // 2]
    scale = float(np.max(dist))
    return bool(shape_min * scale * scale <= 1.0)


def _chi2_and_jacobian(positions: np.ndarray, free: np.ndarray, x_free: np.ndarray, pairs: np.ndarray,
                       dist: np.ndarray, weights: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Chi-square, whitened residuals and whitened Jacobian over the free coordinates."""
    n, dim = positions.shape
    flat = positions.ravel().copy()
    flat[free] = x_free
    x = flat.reshape(n, dim)
    diff = x[pairs[:, 0]] - x[pairs[:, 1]]
    d = np.sqrt((diff * diff).sum(axis=1))
    sw = np.sqrt(weights)
    z = (d - dist) * sw
    unit = diff / np.maximum(d, 1e-12)[:, None]
    jac = np.zeros((len(pairs), n * dim))
    rows = np.arange(len(pairs))
    for a in range(dim):
        jac[rows, pairs[:, 0] * dim + a] = unit[:, a] * sw
        jac[rows, pairs[:, 1] * dim + a] = -unit[:, a] * sw
    return float(z @ z), z, jac[:, free]


def _profile(positions, free, x0, v, t, pairs, dist, weights, z_start) -> tuple[float, np.ndarray]:
    """Minimum chi-square with the coordinates' component along v held at t (Gauss-Newton in
    the orthogonal complement, from ``z_start``); returns it and the complement's offset.
    ``v``: one unit direction (F,), or orthonormal columns (F, k) all held (t = 0 only)."""
    basis = v.reshape(len(v), -1)
    project = np.eye(len(v)) - basis @ basis.T
    v = basis[:, 0]
    offset = z_start
    best, _, _ = _chi2_and_jacobian(positions, free, x0 + t * v + offset, pairs, dist, weights)
    for _ in range(GAUSS_NEWTON_ITERATIONS):
        _, z, jac = _chi2_and_jacobian(positions, free, x0 + t * v + offset, pairs, dist, weights)
        step = project @ np.linalg.lstsq(jac @ project, -z, rcond=None)[0]
        trial = offset + step
        value, _, _ = _chi2_and_jacobian(positions, free, x0 + t * v + trial, pairs, dist, weights)
        if not value < best:
            break
        gain = best - value
        best, offset = value, trial
        if gain < 1e-9 * max(best, 1.0):
            break
    return best, offset


def _profile_minimum(positions, free, x0, null_basis, v, pairs, dist, weights, scale) -> np.ndarray:
    """x0 moved to the profile chi-square's minimum along v: the complement re-fitted with
    every null direction held, then a search along v (the solver's crawl can stop short of the
    line, where the profile still falls: chi-square up to 26 above it at K = 50)."""
    zero = np.zeros_like(x0)
    value, offset = _profile(positions, free, x0, null_basis, 0.0, pairs, dist, weights, zero)
    if value < _chi2_and_jacobian(positions, free, x0, pairs, dist, weights)[0]:
        x0 = x0 + offset

    def profile(t: float) -> float:
        return _profile(positions, free, x0, v, t, pairs, dist, weights, zero)[0]

    # The minimum can be metres away (a K = 50 round stopped 6 m off the line, chi-square 29.7
    # against 3.3 there): scan a geometric grid over the scene's size both ways, then refine
    # between the best grid point's neighbours.
    steps = scale * np.logspace(-4, 0, 29)
    grid = np.concatenate([-steps[::-1], [0.0], steps])
    values = np.array([profile(t) for t in grid])
    k = int(np.argmin(values))
    found = minimize_scalar(profile, bounds=(grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]), method="bounded",
                            options={"xatol": 1e-9 * scale})
    t, value = (found.x, found.fun) if found.fun < values[k] else (grid[k], values[k])
    if value < values[len(steps)]:
        _, offset = _profile(positions, free, x0, v, t, pairs, dist, weights, zero)
        x0 = x0 + t * v + offset
    return x0


def _profile_sigma_points(positions, free, x0, v, pairs, dist, weights, scale) -> list[np.ndarray]:
    """The profile optimum's displacement from x0 at the two points along v (one each side)
    where the profile chi-square has risen by one above its value at x0. Both sides: the fit
    may sit a little off the symmetric optimum, where an iteration-capped solve crawling
    towards the line stopped."""
    base, _ = _profile(positions, free, x0, v, 0.0, pairs, dist, weights, np.zeros_like(x0))
    points = []
    for sign in (1.0, -1.0):
        lo, hi, offset = 0.0, 1e-4 * scale, np.zeros_like(x0)
        while True:
            value, offset = _profile(positions, free, x0, v, sign * hi, pairs, dist, weights, offset)
            if value >= base + 1.0:
                break
            lo, hi = hi, 2.0 * hi
            if hi > scale:
                raise GeometryError("degenerate anchor geometry: the ranges do not bound a direction of the "
                                    "shape within the scene's size (a flexible layout)")
        hi_offset = offset
        for _ in range(BISECTIONS):
            mid = 0.5 * (lo + hi)
            value, mid_offset = _profile(positions, free, x0, v, sign * mid, pairs, dist, weights, hi_offset)
            if value >= base + 1.0:
                hi, hi_offset = mid, mid_offset
            else:
                lo = mid
        points.append(sign * hi * v + hi_offset)
    return points
