"""Levenberg-Marquardt for inter-anchor range problems, built for a few dozen anchors.

A calibration has a handful to a few thousand residuals, so a general solver (scipy's
``least_squares``) spends its time in Python bookkeeping, not arithmetic. This one:

- compiles the problem's *structure* (pairs, which coordinates the gauge fixes) once into
  index arrays and caches it: the env calibrates the same anchors over and over;
- runs the iterations as one compiled loop (``_lm_kernel``, numba): no per-iteration array
  calls, which were ~90 % of a solve at N = 4;
- accumulates the normal equations J^T W J and J^T W r from per-pair blocks (each pair touches
  two anchors: four dim x dim blocks and two gradient entries), so an iteration costs O(pairs),
  not the O(pairs x coordinates^2) of a dense product (~N^4 at N = 64). An extra last
  coordinate absorbs the gauge-fixed ones (no column selection; its step is zero);
- steps with the cost's Hessian (J^T W J plus the residuals' curvature) where it is positive
  definite, else with J^T W J (Gauss-Newton), and only damps after a step that raised the cost.
  Gauss-Newton alone converges linearly along weakly determined directions (3D teams at
  similar heights: ~260 iterations for a 64-anchor first calibration, 5 with the Hessian);
- stops when the step is below ``xtol_sigma`` of the smallest range std: what is left is
  orders of magnitude under the noise. That last step is taken without a new evaluation; the
  residuals are updated to first order (their error is about the step squared over a range,
  ~1e-11 m for the default tolerance).

Robust losses run as iteratively reweighted least squares with the weights of ``robust``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy.linalg.lapack import dpocon, dposv

from uwb_env.localization._lm_kernel import LOSS_CODES, MESSAGES, RCOND_MIN, lm_pairs
from uwb_env.localization.errors import GeometryError


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
    for array in (incidence, column, take, identity, pi, pj):
        array.flags.writeable = False  # shared by every solve with this layout
    return PairStructure(n, dim, n_free, incidence, row0 + ci, row0 + cj, column, take, identity, pi, pj)


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
            ratio each iteration (quadratically when the ranges are consistent); 1e-4 for
            robust losses, whose reweighting converges only linearly.
        ftol: or when the relative cost decrease falls below this.
    """
    if not (isinstance(max_iterations, int | np.integer) and max_iterations >= 1):
        raise ValueError(f"max_iterations={max_iterations!r}: must be an integer >= 1")
    if not (math.isfinite(f_scale) and f_scale > 0):
        raise ValueError(f"f_scale={f_scale!r}: must be a finite number > 0")
    x0 = np.array(x0, dtype=np.float64).reshape(structure.n, structure.dim)
    dist = np.ascontiguousarray(dist, dtype=np.float64)
    inv_var = np.ascontiguousarray(inv_var, dtype=np.float64)
    sqrt_iv = np.sqrt(inv_var)
    linear = loss == "linear"
    if xtol_sigma is None:
        xtol_sigma = 1e-3 if linear else 1e-4
    # floor: steps below ~1e-12 of the scene's size are lost to rounding
    xtol = max(xtol_sigma / float(sqrt_iv.max()), 1e-12 * float(np.abs(dist).max()))
    x, info, r, robust_w, cost, it, status = lm_pairs(
        x0, structure.pi, structure.pj, structure.column, structure.n_free, dist, sqrt_iv, LOSS_CODES[loss],
        float(f_scale), int(max_iterations), xtol * xtol, float(ftol))
    return PairSolution(x, info, r, inv_var * robust_w, float(cost), int(it), status == 1, MESSAGES[status],
                        structure)
