"""Levenberg-Marquardt for inter-anchor range problems, built for a few dozen anchors.

A calibration has a handful to a few hundred residuals, so a general solver (scipy's
``least_squares``) spends its time in Python bookkeeping, not arithmetic. This one keeps the
number of numpy calls per iteration small and fixed:

- The problem's *structure* (pairs, which coordinates the gauge fixes) is compiled once into
  index arrays and cached: the env calibrates the same anchors over and over.
- The normal equations J^T W J and J^T W r are accumulated from per-pair blocks (each pair
  touches two anchors: four dim x dim blocks and two gradient entries) with one ``bincount``
  each, so an iteration costs O(pairs), not the O(pairs x coordinates^2) of a dense product
  (~N^4; at N = 64 that product also spun up BLAS threads that fought over two cores). An
  extra last coordinate absorbs the gauge-fixed ones (no column selection; its step is zero).
- The normal equations are solved by LAPACK's Cholesky (``dposv``), whose call overhead is a
  fraction of ``numpy.linalg.solve``'s.
- It starts as Gauss-Newton (no damping) and only damps after a step that raised the cost.
- It stops when the step is below ``xtol_sigma`` of the smallest range std: what is left is
  orders of magnitude under the noise. That last step is taken without a new evaluation; the
  residuals are updated to first order (their error is about the step squared over a range,
  ~1e-11 m for the default tolerance).

Robust losses run as iteratively reweighted least squares with the weights from ``robust``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy.linalg.lapack import dpocon, dposv

from uwb_env.localization.errors import GeometryError
from uwb_env.localization.robust import irls_weights, robust_cost

# Below this reciprocal condition number of J^T W J the free coordinates are not fixed by
# the ranges (collinear / coplanar anchors, too few pairs for a rigid shape).
RCOND_MIN = 1e-10


@dataclass(frozen=True, eq=False)
class PairStructure:
    """Index arrays of one problem layout (pairs over n anchors, with some coordinates fixed).

    Attributes:
        n, dim: anchors and dimension.
        n_free: number of estimated coordinates F.
        incidence: (P, n) +1 at pair i, -1 at pair j: ``incidence @ x`` are the differences.
        put_i, put_j: (P, dim) flat indices of d r_p / d x_i (and x_j) in a (P, F+1) buffer.
        column: (n*dim,) column of each coordinate; fixed coordinates map to the extra one, F.
        covariance_take: (n*dim, n*dim) flat indices into an (F+1, F+1) matrix that expand it
            to all coordinates (fixed ones read the extra row and column).
        identity: (F+1, F+1) identity (read-only), the right-hand side that inverts.
        pi, pj: (P,) the pairs' anchors.
        block_index: (P, 4, dim, dim) flat indices into (F+1, F+1) of each pair's four blocks
            (ii, jj, ij, ji) of J^T W J; ``grad_index`` (P, 2, dim) of its gradient entries.
    """

    n: int
    dim: int
    n_free: int
    incidence: np.ndarray
    put_i: np.ndarray
    put_j: np.ndarray
    column: np.ndarray
    covariance_take: np.ndarray
    identity: np.ndarray
    pi: np.ndarray
    pj: np.ndarray
    block_index: np.ndarray
    grad_index: np.ndarray


def pair_structure(pairs: np.ndarray, n: int, dim: int, free: np.ndarray) -> PairStructure:
    """The (cached) structure for ``pairs`` (P, 2) and a ``free`` (n*dim,) coordinate mask."""
    pairs = np.ascontiguousarray(pairs, dtype=np.int64)
    free = np.ascontiguousarray(free, dtype=bool)
    return _structure(n, dim, pairs.tobytes(), free.tobytes())


@lru_cache(maxsize=128)
def _structure(n: int, dim: int, pair_bytes: bytes, free_bytes: bytes) -> PairStructure:
    pairs = np.frombuffer(pair_bytes, dtype=np.int64).reshape(-1, 2)
    free = np.frombuffer(free_bytes, dtype=bool)
    n_free = int(free.sum())
    column = np.full(n * dim, n_free, dtype=np.int64)
    column[free] = np.arange(n_free)
    p = len(pairs)
    incidence = np.zeros((p, n))
    incidence[np.arange(p), pairs[:, 0]] = 1.0
    incidence[np.arange(p), pairs[:, 1]] = -1.0
    cols = column.reshape(n, dim)
    row0 = (np.arange(p) * (n_free + 1))[:, None]
    take = column[:, None] * (n_free + 1) + column[None, :]
    identity = np.eye(n_free + 1)
    pi, pj = pairs[:, 0].copy(), pairs[:, 1].copy()
    ci, cj = cols[pi], cols[pj]  # (P, dim) columns of each pair's coordinates
    m = n_free + 1
    block = np.stack([ci[:, :, None] * m + ci[:, None, :], cj[:, :, None] * m + cj[:, None, :],
                      ci[:, :, None] * m + cj[:, None, :], cj[:, :, None] * m + ci[:, None, :]], axis=1)
    grad = np.stack([ci, cj], axis=1)
    for array in (incidence, column, take, identity, pi, pj, block, grad):
        array.flags.writeable = False  # shared by every solve with this layout
    return PairStructure(n, dim, n_free, incidence, row0 + ci, row0 + cj, column, take, identity, pi, pj,
                         block, grad)


_BLOCK_SIGNS = np.array([1.0, 1.0, -1.0, -1.0])[None, :, None, None]
_GRAD_SIGNS = np.array([1.0, -1.0])[None, :, None]


def _unit_vectors(structure: PairStructure, x: np.ndarray, dist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Residuals ||x_i - x_j|| - dist (P,) and unit vectors (x_i - x_j) / ||x_i - x_j|| (P, dim)."""
    diff = x[structure.pi] - x[structure.pj]
    if structure.dim == 2:
        d = np.hypot(diff[:, 0], diff[:, 1])
    else:
        d = np.sqrt((diff * diff).sum(1))
    return d - dist, diff / np.maximum(d, 1e-12)[:, None]


def _normal_equations(structure: PairStructure, v: np.ndarray, wz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """J^T W J (F+1, F+1) and J^T W z (F+1,) from per-pair blocks; ``v`` = whitened, weighted
    unit vectors (the Jacobian rows' nonzero part), ``wz`` the matching residuals. The extra
    coordinate's row and column are reset to the identity's."""
    m = structure.n_free + 1
    outer = v[:, None, :, None] * v[:, None, None, :] * _BLOCK_SIGNS
    a = np.bincount(structure.block_index.ravel(), outer.ravel(), m * m).reshape(m, m)
    g = np.bincount(structure.grad_index.ravel(), ((v * wz[:, None])[:, None, :] * _GRAD_SIGNS).ravel(), m)
    a[-1, :] = 0.0
    a[:, -1] = 0.0
    a[-1, -1] = 1.0
    g[-1] = 0.0
    return a, g


@dataclass
class PairSolution:
    """Outcome of :func:`solve_pair_ranges`.

    ``information`` is J^T W J over the free coordinates at the solution (plus a 1 on the
    extra diagonal entry of the gauge column, which keeps it positive definite and is dropped
    by :meth:`covariance`).
    """

    positions: np.ndarray
    information: np.ndarray
    residuals: np.ndarray
    weights: np.ndarray
    cost: float
    iterations: int
    converged: bool
    message: str
    structure: PairStructure

    def covariance(self) -> np.ndarray:
        """(n*dim, n*dim) inverse information, zeros on the fixed coordinates.

        Raises GeometryError when the ranges do not fix every free coordinate.
        """
        s = self.structure
        info = self.information
        chol, inv, status = dposv(info, s.identity)
        if status == 0:
            # For a PSD matrix the 1-norm is at most sqrt(m) * largest eigenvalue <= sqrt(m) * trace:
            # a cheap bound that errs towards calling a shape degenerate, never towards trusting one
            rcond, _ = dpocon(chol, float(info.trace()) * math.sqrt(len(info)))
        if status != 0 or not rcond > RCOND_MIN:
            raise GeometryError(
                "degenerate anchor geometry: the ranges do not fix every free coordinate "
                "(collinear / coplanar anchors, or too few pairs for a rigid shape)"
            )
        inv[s.n_free] = 0.0
        inv[:, s.n_free] = 0.0
        return inv.take(s.covariance_take)


def pair_residuals(
    structure: PairStructure, x: np.ndarray, dist: np.ndarray, row_scale: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Residuals ||x_i - x_j|| - dist (P,) and the Jacobian buffer (P, F+1), gauge column zero.

    ``row_scale`` (P,) multiplies the Jacobian's rows (the solver passes 1/sigma_p: whitening
    costs nothing extra here).
    """
    diff = structure.incidence @ x
    if structure.dim == 2:
        d = np.hypot(diff[:, 0], diff[:, 1])
    else:
        d = np.sqrt((diff * diff).sum(1))
    scale = 1.0 / np.maximum(d, 1e-12) if row_scale is None else row_scale / np.maximum(d, 1e-12)
    u = diff * scale[:, None]
    jac = np.zeros((len(d), structure.n_free + 1))
    jac.put(structure.put_i, u)
    jac.put(structure.put_j, -u)
    jac[:, -1] = 0.0
    return d - dist, jac


def solve_pair_ranges(
    structure: PairStructure,
    x0: np.ndarray,
    dist: np.ndarray,
    inv_var: np.ndarray,
    loss: str = "linear",
    f_scale: float = 1.0,
    max_iterations: int = 50,
    xtol_sigma: float | None = None,
    ftol: float = 1e-12,
) -> PairSolution:
    """Minimize 0.5 * sum rho(((||x_i - x_j|| - dist_p) / sigma_p)^2) over the free coordinates.

    Args:
        structure: from :func:`pair_structure`; the fixed coordinates keep their ``x0`` values.
        x0: (n, dim) start.
        dist, inv_var: (P,) measured ranges and 1 / sigma_p^2.
        loss, f_scale: robust loss and its scale in whitened units (see ``robust``).
        xtol_sigma: stop when the step's norm is below this fraction of the smallest sigma_p.
            The step is still taken, so what is left is about the next step. Default 1e-3 for
            the linear loss, where Gauss-Newton shrinks steps by about the residual-to-range
            ratio each iteration (quadratically when the ranges are consistent); 1e-6 for
            robust losses, whose reweighting converges only linearly.
        ftol: or when the relative cost decrease falls below this.
    """
    n, dim = structure.n, structure.dim
    column = structure.column
    if not (isinstance(max_iterations, int | np.integer) and max_iterations >= 1):
        raise ValueError(f"max_iterations={max_iterations!r}: must be an integer >= 1")
    if not (math.isfinite(f_scale) and f_scale > 0):
        raise ValueError(f"f_scale={f_scale!r}: must be a finite number > 0")
    x = np.array(x0, dtype=float).reshape(n, dim)
    sqrt_iv = np.sqrt(inv_var)
    linear = loss == "linear"
    if xtol_sigma is None:
        xtol_sigma = 1e-3 if linear else 1e-4
    # floor: steps below ~1e-12 of the scene's size are lost to rounding
    xtol = max(xtol_sigma / float(sqrt_iv.max()), 1e-12 * float(np.abs(dist).max()))
    xtol2 = xtol * xtol
    # z is whitened (divided by sigma_p); robust weights scale it further per step
    r, u = _unit_vectors(structure, x, dist)
    z = r * sqrt_iv
    cost = 0.5 * float(z @ z) if linear else robust_cost(z, loss, f_scale)
    info = None
    lam, message, converged, it = 0.0, "max_iterations reached", False, 0
    for it in range(1, max_iterations + 1):
        if linear:
            root_w = sqrt_iv
            wz = z
        else:
            rw = np.sqrt(irls_weights(z, loss, f_scale))
            root_w, wz = sqrt_iv * rw, z * rw
        a, g = _normal_equations(structure, u * root_w[:, None], wz)
        while True:
            if lam:
                diag = np.diag(a).copy()
                diag[diag <= 0] = 1.0
                _, step, status = dposv(a + np.diag(lam * diag), g)
            else:
                _, step, status = dposv(a, g)
            if status == 0:
                delta = step.take(column).reshape(n, dim)  # the gauge coordinates read step[F] = 0
                if float(step @ step) <= xtol2:
                    x -= delta
                    # residuals to first order (their error is ~ step^2 / range)
                    z = z - sqrt_iv * ((delta[structure.pi] - delta[structure.pj]) * u).sum(1)
                    r = z / sqrt_iv
                    cost = 0.5 * float(z @ z) if linear else robust_cost(z, loss, f_scale)
                    message, converged = "converged", True
                    if linear:
                        info = a  # J^T W J barely moves over a sub-xtol step
                    break
                trial = x - delta
                r_new, u_new = _unit_vectors(structure, trial, dist)
                z_new = r_new * sqrt_iv
                cost_new = 0.5 * float(z_new @ z_new) if linear else robust_cost(z_new, loss, f_scale)
                if cost_new <= cost:  # False for NaN
                    break
            lam = max(lam * 10.0, 1e-6)
            if lam > 1e12:
                message = "no decrease possible" if status == 0 else "singular normal equations"
                break
        if message != "max_iterations reached":
            break
        small_gain = cost - cost_new <= ftol * max(cost, 1e-300)
        x, r, z, u, cost = trial, r_new, z_new, u_new, cost_new
        lam = lam / 10.0 if lam > 1e-6 else 0.0
        if small_gain:
            message, converged = "converged", True
            break
    robust_w = np.ones_like(z) if linear else irls_weights(z, loss, f_scale)
    if info is None:
        info, _ = _normal_equations(structure, u * (sqrt_iv * np.sqrt(robust_w))[:, None], z)
    return PairSolution(x, info, r, inv_var * robust_w, cost, it, converged, message, structure)
