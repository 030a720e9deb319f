"""Anchor autocalibration from inter-anchor ranges (Martinez Almansa et al., Sec. 3).

First calibration (no prior), the paper's rules: anchor 0 at the origin, anchor 1 on +x,
the others in +y (which fixes the reflection: see ``alignment.paper_frame``; in 3D the
anchor farthest off the x axis also fixes the rotation about x). Initial positions by
trilateration from the ranges to anchors 0 and 1; each further anchor's y sign is checked
against its ranges to the anchors already placed, which keeps the paper's solution where its
assumption holds and repairs it where it does not. Classical MDS takes over when
trilateration is ill-posed. Then weighted least squares over every available pair.

Later calibrations (a prior = the anchors' current on-board estimates): only "anchor 0 is the
origin" is assumed. The shape is solved starting from the prior in an internal gauge
(anchor 0 at the origin, the anchor farthest from it on +x, the most off-axis one in +y),
then placed in the running frame:

- ``gauge="anchor0"`` (paper): anchor 0 keeps its prior position; rotation *and reflection*
  are the best orthogonal alignment, about anchor 0, of the solved shape to the prior.
  Reflection is free because ranges cannot tell mirror images apart: the prior decides.
- ``gauge="prior"``: best rigid alignment (translation too) to all anchors' priors, which
  averages the odometry errors of all anchors instead of trusting anchor 0's alone.

The reported covariance is (J^T W J)^-1 in the internal gauge, rotated into the output frame:
it is the uncertainty of the shape with the gauge (anchor 0, the x axis) held fixed.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy.sparse.csgraph import shortest_path

from uwb_env.localization.alignment import frame_refs, paper_frame, rigid_align
from uwb_env.localization.errors import (
    DisconnectedGraphError,
    GeometryError,
    InvalidRangeError,
    TooFewAnchorsError,
)
from uwb_env.localization.pair_solver import PairStructure, pair_structure, solve_pair_ranges
from uwb_env.localization.robust import check_loss
from uwb_env.measurements import RangeMatrix, _pair_index

GAUGES = ("anchor0", "prior")
INITIALIZERS = ("auto", "trilateration", "mds")


@dataclass
class CalibrationResult:
    """Solution of one calibration.

    Attributes:
        positions: (n, dim) anchor positions in the output frame.
        covariance: (n*dim, n*dim) covariance (gauge held fixed; zeros on gauge coordinates).
        pairs: (P, 2) anchor pairs used; ``ranges_m`` their (combined) ranges.
        residuals_m: (P,) fitted minus measured range per pair.
        iterations, cost, converged, message: optimizer diagnostics.
        initializer: "trilateration", "mds", "prior", or "prior+trilateration" / "prior+mds"
            when the prior's solution was replaced by a restart from the ranges alone.
        gauge_refs: anchors fixing the internal gauge (origin, +x, +y[, +z]).
    """

    positions: np.ndarray
    covariance: np.ndarray
    pairs: np.ndarray
    ranges_m: np.ndarray
    residuals_m: np.ndarray
    range_var_m2: np.ndarray
    iterations: int
    cost: float
    converged: bool
    message: str
    initializer: str
    gauge_refs: tuple[int, ...]

    @property
    def n_anchors(self) -> int:
        return self.positions.shape[0]

    def anchor_covariance(self) -> np.ndarray:
        """(n, dim, dim) per-anchor covariance blocks."""
        n, dim = self.positions.shape
        idx = np.arange(n)
        return self.covariance.reshape(n, dim, n, dim)[idx, :, idx, :]

    def position_std_m(self) -> np.ndarray:
        """(n,) sqrt of the trace of each anchor's covariance block."""
        return np.sqrt(np.trace(self.anchor_covariance(), axis1=1, axis2=2))

    @property
    def rms_residual_m(self) -> float:
        return float(np.sqrt(np.mean(self.residuals_m**2))) if len(self.residuals_m) else 0.0

    @property
    def normalized_residuals(self) -> np.ndarray:
        return self.residuals_m / np.sqrt(self.range_var_m2)


def calibrate_anchors(
    ranges: RangeMatrix | np.ndarray,
    *,
    dim: int = 2,
    prior: np.ndarray | None = None,
    gauge: str = "anchor0",
    loss: str = "linear",
    f_scale: float = 2.0,
    range_std_m: float | None = None,
    min_range_std_m: float = 0.03,
    initializer: str = "auto",
    max_iterations: int = 50,
    restart_sigmas: float = 8.0,
) -> CalibrationResult:
    """Estimate all anchor positions from a calibration round.

    Args:
        ranges: bias-corrected :class:`RangeMatrix` (per ordered pair mean/std/count), or an
            (n, n) matrix of ranges (NaN = missing): one range per unordered pair, the two
            directions averaged when both are given, with std ``range_std_m``.
        dim: 2 or 3.
        prior: (n, dim) current on-board estimates; ``None`` for the first calibration.
        gauge: how a later calibration is placed in the running frame (module docstring).
        loss: ``linear``, ``huber``, ``soft_l1`` or ``cauchy`` (robust to NLOS outliers).
        f_scale: robust-loss scale in units of the range std (2 = start down-weighting at 2 sigma).
        range_std_m: known per-range std; if given it replaces the per-pair sample std.
        min_range_std_m: floor on the per-pair std (a std from K=5 samples can be ~0).
        initializer: ``auto`` (trilateration, MDS fallback), ``trilateration`` or ``mds``.
        max_iterations: Gauss-Newton / Levenberg-Marquardt iterations (``pair_solver``).
        restart_sigmas: with a prior, a residual above this many range stds triggers a second
            solve from the ranges alone (trilateration/MDS); the lower cost wins.

    Raises:
        TooFewAnchorsError, InvalidRangeError, DisconnectedGraphError, GeometryError,
        ValueError (bad arguments).
    """
    check_loss(loss)
    if gauge not in GAUGES:
        raise ValueError(f"gauge={gauge!r}: must be one of {GAUGES}")
    if initializer not in INITIALIZERS:
        raise ValueError(f"initializer={initializer!r}: must be one of {INITIALIZERS}")
    if dim not in (2, 3):
        raise ValueError(f"dim={dim!r}: must be 2 or 3")
    pairs, dist, var, n = _pair_data(ranges, range_std_m, min_range_std_m)
    if n < dim + 1:
        raise TooFewAnchorsError(f"{n} anchors: a {dim}D calibration needs at least {dim + 1}")
    if len(pairs) < n * (n - 1) // 2:
        _check_connected(pairs, n)
    if prior is not None:
        prior = np.asarray(prior, dtype=float)
        if prior.shape != (n, dim) or not np.isfinite(prior).all():
            raise ValueError(f"prior: expected finite ({n}, {dim}) positions, got shape {prior.shape}")

    if prior is None:
        x0, init_name = _initial_positions(pairs, dist, n, dim, initializer)
        if dim == 2 and init_name == "trilateration":
            # Trilateration already places anchor 0 at the origin and anchor 1 on +x: that is
            # the internal gauge, up to the mirror image the final sign rule settles.
            refs, x0_gauge = (0, 1), x0
        else:
            refs = frame_refs(x0)
            rot0, trans0 = paper_frame(x0, refs)
            x0_gauge = x0 @ rot0.T + trans0
    else:
        refs = _gauge_refs(prior)
        x0, init_name = prior, "prior"
        rot0, trans0 = paper_frame(prior, refs)
        x0_gauge = x0 @ rot0.T + trans0

    structure = _structure(pairs, n, dim, refs)
    inv_var = 1.0 / var

    def solve(start_gauge: np.ndarray):
        if loss != "linear":
            # Robust losses are non-convex: start them from the plain least-squares solution so
            # an outlier-corrupted initial guess does not trap them in a wrong minimum.
            start_gauge = solve_pair_ranges(structure, start_gauge, dist, inv_var, "linear", 1.0,
                                            max_iterations).positions
        return solve_pair_ranges(structure, start_gauge, dist, inv_var, loss, f_scale, max_iterations)

    out = solve(x0_gauge)
    if prior is not None and float(np.max(np.abs(out.residuals) * np.sqrt(inv_var))) > restart_sigmas:
        # A prior far off (long drift) can sit in the basin of a folded shape (one anchor
        # mirrored across a line through two others): the residuals then stay metres large.
        # Restart from the ranges alone, in the same gauge, and keep the lower cost.
        cold, cold_name = _initial_positions(pairs, dist, n, dim, "auto")
        rot_c, trans_c = paper_frame(cold, refs)
        out_cold = solve(cold @ rot_c.T + trans_c)
        if out_cold.cost < out.cost:
            out, init_name = out_cold, "prior+" + cold_name
    x_gauge = out.positions
    cov_gauge = out.covariance()

    if prior is None:
        # Re-apply the frame's sign rules to the solution (only axis flips here): the cost is
        # mirror-invariant, so the optimizer may have crossed to the other side.
        signs = _gauge_flip(x_gauge, refs)
        if signs is None:
            positions, covariance = x_gauge, cov_gauge
        else:
            positions = x_gauge * signs
            flips = np.tile(signs, n)
            covariance = cov_gauge * flips[:, None] * flips[None, :]  # exact +-1: no leakage
    else:
        pivot = 0 if gauge == "anchor0" else None
        rot, trans = rigid_align(x_gauge, prior, allow_reflection=True, pivot=pivot)
        positions = x_gauge @ rot.T + trans
        covariance = _rotate_covariance(cov_gauge, rot, n, dim)
    return CalibrationResult(
        positions=positions,
        covariance=covariance,
        pairs=pairs,
        ranges_m=dist,
        residuals_m=out.residuals,
        range_var_m2=var,
        iterations=out.iterations,
        cost=out.cost,
        converged=out.converged,
        message=out.message,
        initializer=init_name,
        gauge_refs=refs,
    )


def _gauge_flip(x_gauge: np.ndarray, refs: tuple[int, ...]) -> np.ndarray | None:
    """(dim,) axis signs that put a gauge-frame solution in the paper frame, None if none flip.

    The gauge anchors are where ``paper_frame`` puts them (origin, +-x axis, xy-plane), so its
    rotation is diagonal. Degenerate shapes never get here: their information matrix is
    singular, which ``PairSolution.covariance`` reports.
    """
    if x_gauge.shape[1] == 3:
        signs = np.diag(paper_frame(x_gauge, refs)[0]).copy()
        return None if signs.min() > 0 else signs
    origin = x_gauge[refs[0]]
    sx = 1.0 if x_gauge[refs[1], 0] >= origin[0] else -1.0
    sy = 1.0 if float(x_gauge[:, 1].sum()) >= len(x_gauge) * origin[1] else -1.0
    return None if sx > 0 and sy > 0 else np.array([sx, sy])


def _rotate_covariance(cov: np.ndarray, rot: np.ndarray, n: int, dim: int) -> np.ndarray:
    """Covariance of x @ rot.T per anchor: (I_n kron R) cov (I_n kron R)^T."""
    left = np.matmul(rot, cov.reshape(n, dim, n * dim)).reshape(n * dim, n, dim)
    return np.matmul(left, rot.T).reshape(n * dim, n * dim)


# -- input handling ----------------------------------------------------------------------------
def _pair_data(ranges, range_std_m, min_range_std_m):
    if range_std_m is not None and not (np.isfinite(range_std_m) and range_std_m > 0):
        raise ValueError(f"range_std_m={range_std_m!r}: must be > 0")
    if isinstance(ranges, RangeMatrix):
        complete = ranges.complete_symmetric(min_range_std_m, range_std_m)
        if complete is not None:  # the usual round: nothing to validate further
            return (*complete, ranges.n_anchors)
        mean, count = np.asarray(ranges.mean_m, float), np.asarray(ranges.count)
        bad = (count > 0) & ~np.isfinite(mean)
        if bad.any():
            i, j = np.argwhere(bad)[0]
            raise InvalidRangeError(f"range ({i}, {j}) = {mean[i, j]!r} with count {count[i, j]}: not finite")
        matrix = ranges
    else:
        mean = np.asarray(ranges, dtype=float)
        if mean.ndim != 2 or mean.shape[0] != mean.shape[1]:
            raise InvalidRangeError(f"ranges: expected a square matrix, got shape {mean.shape}")
        if np.isinf(mean).any():
            i, j = np.argwhere(np.isinf(mean))[0]
            raise InvalidRangeError(f"range ({i}, {j}) = {mean[i, j]!r}: not finite")
        # One range per unordered pair: the two directions (if both given) are averaged.
        both = np.stack([mean, mean.T])
        given = np.isfinite(both)
        n_given = given.sum(0)
        sym = np.where(n_given > 0, np.where(given, both, 0.0).sum(0) / np.maximum(n_given, 1), np.nan)
        upper = np.triu(np.isfinite(sym), 1)
        std = np.full(mean.shape, range_std_m if range_std_m is not None else min_range_std_m)
        matrix = RangeMatrix(np.where(upper, sym, np.nan), std, upper.astype(int))
    if np.any(mean < 0):  # NaN compares False
        negative = (mean < 0) & ~np.eye(mean.shape[0], dtype=bool)
        if negative.any():
            i, j = np.argwhere(negative)[0]
            raise InvalidRangeError(f"range ({i}, {j}) = {mean[i, j]!r}: negative")
    if range_std_m is not None:
        pairs, dist, var = matrix.symmetric(std_m=float(range_std_m))
    else:
        pairs, dist, var = matrix.symmetric(min_std_m=min_range_std_m)
    if not np.all(var > 0):
        raise ValueError("range variances must be > 0: give range_std_m or min_range_std_m > 0")
    return pairs, dist, var, mean.shape[0]


def _check_connected(pairs: np.ndarray, n: int) -> None:
    # Union-find: for a few dozen anchors this is far cheaper than scipy.sparse.csgraph.
    parent = list(range(n))

    def root(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for i, j in pairs.tolist():
        parent[root(i)] = root(j)
    roots = [root(a) for a in range(n)]
    if len(set(roots)) > 1:
        groups = [[a for a in range(n) if roots[a] == r] for r in dict.fromkeys(roots)]
        raise DisconnectedGraphError(f"range graph has {len(groups)} disconnected components: {groups}")


@lru_cache(maxsize=64)
def _complete_structure(n: int, dim: int, refs: tuple[int, ...]) -> PairStructure:
    return pair_structure(_pair_index(n)[0], n, dim, _free_mask(n, dim, refs))


def _structure(pairs: np.ndarray, n: int, dim: int, refs: tuple[int, ...]) -> PairStructure:
    if pairs is _pair_index(n)[0]:  # every pair measured: the usual round, keyed cheaply
        return _complete_structure(n, dim, refs)
    return pair_structure(pairs, n, dim, _free_mask(n, dim, refs))


def _free_mask(n: int, dim: int, refs: tuple[int, ...]) -> np.ndarray:
    """Coordinates the solver estimates; the gauge anchors' fixed ones are excluded."""
    free = np.ones((n, dim), dtype=bool)
    for level, anchor in enumerate(refs[:dim]):
        free[anchor, level:] = False  # origin: all fixed; +x ref: y(,z) fixed; +y ref (3D): z fixed
    return free.ravel()


def _gauge_refs(prior: np.ndarray) -> tuple[int, ...]:
    """Anchor 0, the anchor farthest from it (+x), and in 3D the one farthest off that axis."""
    b = int(np.argmax(np.linalg.norm(prior - prior[0], axis=1)))
    if b == 0:
        raise GeometryError("prior anchors all coincide: the frame cannot be fixed")
    return frame_refs(prior, 0, b)


# -- initializers ------------------------------------------------------------------------------
def _initial_positions(pairs, dist, n, dim, initializer):
    all_pairs, upper, lower = _pair_index(n)
    if pairs is not all_pairs:
        upper, lower = pairs[:, 0] * n + pairs[:, 1], pairs[:, 1] * n + pairs[:, 0]
    full = np.full((n, n), np.nan)
    full.put(upper, dist)
    full.put(lower, dist)
    full.flat[:: n + 1] = 0.0
    if initializer in ("auto", "trilateration"):
        try:
            return trilaterate_initial(full, dim), "trilateration"
        except GeometryError:
            if initializer == "trilateration":
                raise
    return classical_mds(full, dim), "mds"


def trilaterate_initial(full: np.ndarray, dim: int) -> np.ndarray:
    """The paper's first-calibration start: anchors from their ranges to anchors 0 and 1.

    Anchor 0 at the origin, 1 on +x, |y| = sqrt(d0k^2 - x_k^2). In 2D the anchor farthest off the
    x axis is placed at +y, every other anchor takes the y sign that fits its range to that one,
    then (with 5+ anchors) the sign that best fits its ranges to all the others as placed by
    that first pass; the mirror image is settled afterwards by the frame's sign rule. In 3D
    anchors are placed in turn, each with the z sign that fits the anchors already placed.
    """
    n = full.shape[0]
    needed = [0, 1, 2] if dim == 3 else [0, 1]
    if np.isnan(full[: len(needed)].sum()):
        raise GeometryError(f"trilateration needs every range to anchors {needed}")
    d01 = full[0, 1]
    scale = float(np.fmax.reduce(full, axis=None))  # max ignoring NaN (nanmax is slower)
    if d01 < 1e-3 * scale:
        raise GeometryError(f"anchors 0 and 1 are {d01:.3g} m apart: cannot define the x axis")
    if dim == 2:
        return _trilaterate_2d(full, d01, scale)
    x = np.zeros((n, dim))
    x[1, 0] = d01
    for k in range(2, n):
        xk = (full[0, k] ** 2 - full[1, k] ** 2 + d01**2) / (2 * d01)
        rest2 = max(full[0, k] ** 2 - xk**2, 0.0)
        x[k] = _best_candidate(_trilaterate_3d(full, x, k, xk, rest2, scale), full[k, :k], x[:k])
    return x


def _trilaterate_2d(full: np.ndarray, d01: float, scale: float) -> np.ndarray:
    d0sq = full[0] * full[0]
    xs = (d0sq - full[1] * full[1] + d01 * d01) / (2 * d01)
    ys = np.sqrt(np.maximum(d0sq - xs * xs, 0.0))
    xs[:2] = 0.0, d01  # exactly, not up to rounding: these are the gauge's fixed coordinates
    ys[:2] = 0.0
    if ys[2:].max() < 1e-6 * scale:
        raise GeometryError("anchors are collinear: trilateration cannot place them off the x axis")
    if len(xs) > 3:
        # Mirror candidates (x, +y) and (x, -y): keep the one that better fits the range to the
        # anchor farthest off the x axis (taken at +y; the final sign rule picks the mirror).
        ref = 2 + int(np.argmax(ys[2:]))
        dx = xs - xs[ref]
        flip = np.abs(np.hypot(dx, ys + ys[ref]) - full[ref]) < np.abs(np.hypot(dx, ys - ys[ref]) - full[ref])
        flip[:2] = False
        flip[ref] = False
        ys[flip] *= -1.0
    if len(xs) > 4:
        # Second pass: the sign that best fits the ranges to all other anchors as placed by the
        # first (points as complex numbers; the diagonal and missing ranges count nothing).
        n = len(xs)
        placed = xs + 1j * ys
        up = xs + 1j * np.abs(ys)
        misfit_up = np.abs(up[:, None] - placed) - full
        misfit_down = np.abs(up.conj()[:, None] - placed) - full
        misfit_up.flat[:: n + 1] = 0.0
        misfit_down.flat[:: n + 1] = 0.0
        # fmax: a missing range (NaN) costs 0
        cost_up = np.add.reduce(np.fmax(misfit_up * misfit_up, 0.0), 1)
        cost_down = np.add.reduce(np.fmax(misfit_down * misfit_down, 0.0), 1)
        sign = np.where(cost_down < cost_up, -1.0, 1.0)
        sign[:2] = sign[ref] = 1.0  # the reference stays at +y
        ys = np.abs(ys) * sign
    x = np.empty((len(xs), 2))
    x[:, 0], x[:, 1] = xs, ys
    return x


def _trilaterate_3d(full, x, k, xk, rest2, scale):
    if k == 2:
        return np.array([[xk, np.sqrt(rest2), 0.0]])
    x2, y2 = x[2, 0], x[2, 1]
    if abs(y2) < 1e-6 * scale:  # relative: rounding leaves ~1e-8 of a collinear anchor's y
        raise GeometryError("anchors 0, 1, 2 are collinear: cannot fix the 3D frame")
    yk = (full[0, k] ** 2 - full[2, k] ** 2 + x2**2 + y2**2 - 2 * xk * x2) / (2 * y2)
    zk = np.sqrt(max(full[0, k] ** 2 - xk**2 - yk**2, 0.0))
    return np.array([[xk, yk, zk], [xk, yk, -zk]])


def _best_candidate(candidates, ranges_to_placed, placed):
    if len(candidates) == 1:
        return candidates[0]
    ok = np.isfinite(ranges_to_placed)
    errs = [np.nansum((np.linalg.norm(placed[ok] - c, axis=1) - ranges_to_placed[ok]) ** 2) for c in candidates]
    return candidates[int(np.argmin(errs))]


def classical_mds(full: np.ndarray, dim: int) -> np.ndarray:
    """Classical MDS on the range matrix (missing entries filled by shortest paths)."""
    filled = full.copy()
    if np.isnan(filled).any():
        graph = np.where(np.isnan(filled), 0.0, filled)
        filled = shortest_path(graph, method="D", directed=False)
    n = filled.shape[0]
    centering = np.eye(n) - 1.0 / n
    gram = -0.5 * centering @ (filled**2) @ centering
    vals, vecs = np.linalg.eigh(gram)
    order = np.argsort(vals)[::-1][:dim]
    if vals[order[-1]] <= 1e-9 * max(vals[order[0]], 1e-300):
        raise GeometryError(f"anchors span fewer than {dim} dimensions (collinear or coplanar)")
    return vecs[:, order] * np.sqrt(vals[order])
