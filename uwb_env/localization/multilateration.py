"""Tag positioning by least-squares multilateration, vectorized over many tags.

Start: the linearized closed form. With s = ||p||^2 every range gives a linear equation
``-2 a_i . p + s = r_i^2 - ||a_i||^2`` in (p, s), solved by weighted least squares per tag
(needs dim + 1 ranges). Then Gauss-Newton on the true ranges, optionally with IRLS robust
weights and with the anchors' own position covariance folded into each range's variance
(var_i = sigma^2 + u_i^T Sigma_a_i u_i). Tags are independent, so all the linear algebra is
batched: (T, dim, dim) systems solved at once.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy.special import chdtri

from uwb_env.localization._lm_kernel import LOSS_CODES
from uwb_env.localization._tracking_kernel import (
    TAG_AMBIGUOUS,
    TAG_NO_FIX,
    TAG_OK,
    TAG_POOR_FIT,
    mirror_check_2d,
    tag_step_2d,
    track_2d,
)
from uwb_env.localization.errors import InvalidPositionError, InvalidRangeError
from uwb_env.localization.robust import check_loss, irls_weights

OK, TOO_FEW_RANGES, DEGENERATE, NOT_CONVERGED = 0, 1, 2, 3
STATUS_NAMES = {OK: "ok", TOO_FEW_RANGES: "too_few_ranges", DEGENERATE: "degenerate", NOT_CONVERGED: "not_converged"}


@dataclass
class TagFixResult:
    """Batch of tag fixes.

    Attributes:
        positions: (T, dim); NaN where ``status`` is not OK.
        covariance: (T, dim, dim) (J^T W J)^-1; NaN where not OK.
        gdop: (T,) geometric dilution of precision sqrt(trace((J^T J)^-1)); NaN where not OK.
        residual_rms_m: (T,) RMS of fitted minus measured range.
        n_ranges: (T,) usable ranges per tag.
        status: (T,) OK=0, TOO_FEW_RANGES=1, DEGENERATE=2, NOT_CONVERGED=3.
        iterations: Gauss-Newton iterations run.
    """

    positions: np.ndarray
    covariance: np.ndarray
    gdop: np.ndarray
    residual_rms_m: np.ndarray
    n_ranges: np.ndarray
    status: np.ndarray
    iterations: int

    @property
    def ok(self) -> np.ndarray:
        return self.status == OK

    def status_names(self) -> list[str]:
        return [STATUS_NAMES[int(s)] for s in self.status]


def locate_tags(
    anchors: np.ndarray,
    ranges_m: np.ndarray,
    range_std_m: float | np.ndarray,
    *,
    anchor_covariance: np.ndarray | None = None,
    loss: str = "linear",
    f_scale: float = 2.0,
    initial: np.ndarray | None = None,
    max_iterations: int = 10,
    tol_m: float = 1e-6,
    with_covariance: bool = True,
    restart_residual_m: float | None = None,
) -> TagFixResult:
    """Locate T tags from their ranges to N anchors.

    Args:
        anchors: (N, dim) anchor positions.
        ranges_m: (T, N) bias-corrected ranges; NaN where missing.
        range_std_m: scalar or (T, N) std of each range.
        anchor_covariance: optional (N, dim, dim) anchor position covariance.
        loss, f_scale: robust loss (see ``robust``) and its scale in sigmas. With
            ``anchor_covariance`` a sigma includes the anchor's predicted error along the line
            of sight; where that covariance carries the frame's uncertainty (a team calibration
            in a fixed gauge), a stale anchor's bias sits well inside 3 of them and only a scale
            near one down-weighs it (the env uses 0.7: ``SolverConfig.tag_f_scale_sigmas``).
        initial: optional (T, dim) warm start (e.g. the previous fix); rows with NaN fall back
            to the closed form.
        max_iterations, tol_m: Gauss-Newton stopping rule (largest step below ``tol_m``).
        with_covariance: compute covariance and GDOP (skip when tracking in a hot loop).
        restart_residual_m: warm-started tags whose RMS residual exceeds this are solved again
            from the closed form, and the lower residual wins (a stale warm start can sit in a
            wrong minimum, e.g. mirrored across a line of anchors, and would never leave it).
    """
    result = _locate(anchors, ranges_m, range_std_m, anchor_covariance, loss, f_scale, initial, max_iterations,
                     tol_m, with_covariance)
    if restart_residual_m is None or initial is None:
        return result
    warm = np.isfinite(np.asarray(initial, dtype=float)).all(axis=1)
    rows = np.flatnonzero(warm & ~(result.residual_rms_m <= restart_residual_m))
    if len(rows) == 0:
        return result
    std = np.asarray(range_std_m, dtype=float)
    cold = _locate(anchors, np.atleast_2d(ranges_m)[rows], std[rows] if std.ndim == 2 else std, anchor_covariance,
                   loss, f_scale, None, max(max_iterations, 10), tol_m, with_covariance)
    better = cold.ok & ~(cold.residual_rms_m >= result.residual_rms_m[rows])
    take = rows[better]
    for name in ("positions", "covariance", "gdop", "residual_rms_m", "n_ranges", "status"):
        getattr(result, name)[take] = getattr(cold, name)[better]
    return result


def _check_tag_inputs(anchors, ranges_m, range_std_m) -> None:
    """Typed errors instead of NaN fixes: NaN marks a missing range; anything else must be usable."""
    if not np.isfinite(anchors).all():
        raise InvalidPositionError(f"anchors: non-finite position {anchors[~np.isfinite(anchors).all(1)][0]}")
    bad = np.isinf(ranges_m) | (ranges_m < 0)
    if bad.any():
        raise InvalidRangeError(f"ranges_m: range {ranges_m[bad][0]} (ranges must be >= 0, NaN when missing)")
    std = np.broadcast_to(np.asarray(range_std_m, dtype=float), ranges_m.shape)
    bad = np.isfinite(ranges_m) & ~((std > 0) & np.isfinite(std))
    if bad.any():
        raise InvalidRangeError(f"range_std_m: {std[bad][0]} for a measured range (must be finite and > 0)")


def _locate(anchors, ranges_m, range_std_m, anchor_covariance, loss, f_scale, initial, max_iterations, tol_m,
            with_covariance) -> TagFixResult:
    check_loss(loss)
    anchors = np.asarray(anchors, dtype=float)
    ranges_m = np.atleast_2d(np.asarray(ranges_m, dtype=float))
    n_tags, n_anchors = ranges_m.shape
    dim = anchors.shape[1]
    if anchors.shape[0] != n_anchors:
        raise ValueError(f"ranges_m has {n_anchors} columns but anchors has {anchors.shape[0]} rows")
    _check_tag_inputs(anchors, ranges_m, range_std_m)
    valid = np.isfinite(ranges_m)
    n_ranges = valid.sum(axis=1)
    enough = n_ranges >= dim + 1
    r = np.where(valid, ranges_m, 0.0)
    base_var = np.broadcast_to(np.asarray(range_std_m, dtype=float) ** 2, r.shape)
    base_iv = np.where(valid, 1.0 / base_var, 0.0)

    warm = np.zeros(n_tags, dtype=bool)
    if initial is not None:
        init = np.asarray(initial, dtype=float)
        warm = np.isfinite(init).all(axis=1)
    if warm.all():
        p = init.copy()
    else:
        p = _closed_form(anchors, r, base_iv * enough[:, None], dim)
        if warm.any():
            p = np.where(warm[:, None], init, p)
        p = np.where(np.isfinite(p), p, 0.0)

    solve = _gauss_newton_2d if dim == 2 else _gauss_newton_nd
    p, iterations = solve(p, anchors, r, base_var, base_iv, valid, enough, anchor_covariance,
                          loss, f_scale, max_iterations, tol_m)
    if dim == 2 and not with_covariance:
        return _light_result(p, anchors, r, valid, n_ranges, enough, iterations)

    diff = p[:, None, :] - anchors[None, :, :]
    dist = np.sqrt((diff * diff).sum(-1))
    u = diff / np.maximum(dist, 1e-12)[..., None]
    iv = _inverse_variance(base_var, base_iv, u, anchor_covariance, valid)
    res = np.where(valid, dist - r, 0.0)
    w = iv * (irls_weights(res * np.sqrt(iv), loss, f_scale) if loss != "linear" else 1.0)
    info = np.einsum("tai,taj->tij", u * w[..., None], u)
    geo = np.einsum("tai,taj->tij", u * valid[..., None], u)
    eig = np.linalg.eigvalsh(geo)
    status = _status(p, enough, eig[:, 0], eig[:, -1])
    good = status == OK
    cov = np.full((n_tags, dim, dim), np.nan)
    gdop = np.full(n_tags, np.nan)
    if good.any():
        cov[good] = np.linalg.inv(info[good])
        gdop[good] = np.sqrt(np.trace(np.linalg.inv(geo[good]), axis1=1, axis2=2))
    positions = np.where(good[:, None], p, np.nan)
    rms = np.sqrt((res**2).sum(1) / np.maximum(n_ranges, 1))
    return TagFixResult(positions, cov, gdop, rms, n_ranges, status, iterations)


def _status(p, enough, eig_min, eig_max) -> np.ndarray:
    """Per-tag status from range counts, the geometry's eigenvalues and finiteness."""
    status = np.full(len(p), OK)
    status[~enough] = TOO_FEW_RANGES
    status[enough & (eig_min <= 1e-8 * np.maximum(eig_max, 1e-300))] = DEGENERATE
    status[(status == OK) & ~np.isfinite(p).all(axis=1)] = NOT_CONVERGED
    return status


def _gauss_newton_nd(p, anchors, r, base_var, base_iv, valid, enough, anchor_cov, loss, f_scale, iters, tol):
    """Gauss-Newton for any dimension, batched over tags with einsum / batched solves."""
    dim = anchors.shape[1]
    it = 0
    for it in range(1, iters + 1):
        diff = p[:, None, :] - anchors[None, :, :]
        dist = np.sqrt((diff * diff).sum(-1))
        u = diff / np.maximum(dist, 1e-12)[..., None]
        iv = _inverse_variance(base_var, base_iv, u, anchor_cov, valid)
        res = dist - r
        w = iv * (irls_weights(res * np.sqrt(iv), loss, f_scale) if loss != "linear" else 1.0)
        uw = u * w[..., None]
        hess = np.einsum("tai,taj->tij", uw, u) + 1e-12 * np.eye(dim)
        grad = np.einsum("tai,ta->ti", uw, res)
        step = -np.linalg.solve(hess, grad[..., None])[..., 0]
        step[~enough] = 0.0
        p = p + step
        if np.abs(step).max() < tol:
            break
    return p, it


def _gauss_newton_2d(p, anchors, r, base_var, base_iv, valid, enough, anchor_cov, loss, f_scale, iters, tol):
    """Gauss-Newton for planar tags sharing one set of anchors (see :func:`_gn_steps_2d`)."""
    cov = None if anchor_cov is None else (anchor_cov[:, 0, 0], anchor_cov[:, 0, 1], anchor_cov[:, 1, 1])
    px, py, it = _gn_steps_2d(anchors[:, 0], anchors[:, 1], p[:, 0].copy(), p[:, 1].copy(), r, base_var, base_iv,
                              valid, enough, cov, loss, f_scale, iters, tol)
    return np.column_stack([px, py]), it


def _gn_steps_2d(ax, ay, px, py, r, base_var, base_iv, valid, enough, cov, loss, f_scale, iters, tol):
    """Planar Gauss-Newton steps with the 2x2 normal equations written out (no einsum, no
    batched LAPACK): the tracking hot path. Anchor coordinates ``ax, ay`` broadcast against
    the tag axis (shared anchors, or one set per group of tags); ``cov`` is the anchors'
    (c00, c01, c11) covariance entries or None; stops early once every step is below ``tol``."""
    it = 0
    for it in range(1, iters + 1):
        dx, dy = px[..., None] - ax, py[..., None] - ay
        dist = np.maximum(np.hypot(dx, dy), 1e-12)
        ux, uy = dx / dist, dy / dist
        if cov is None:
            iv = base_iv
        else:  # var_i = sigma^2 + u^T Sigma_a u
            c00, c01, c11 = cov
            iv = np.where(valid, 1.0 / (base_var + ux * ux * c00 + 2 * ux * uy * c01 + uy * uy * c11), 0.0)
        res = np.where(valid, dist - r, 0.0)
        w = iv if loss == "linear" else iv * irls_weights(res * np.sqrt(iv), loss, f_scale)
        wx, wy = w * ux, w * uy
        a, b, c = (wx * ux).sum(-1), (wx * uy).sum(-1), (wy * uy).sum(-1)
        gx, gy = (wx * res).sum(-1), (wy * res).sum(-1)
        det = a * c - b * b
        det = np.where(enough & (det > 1e-300), det, np.inf)
        sx, sy = -(c * gx - b * gy) / det, -(a * gy - b * gx) / det
        px, py = px + sx, py + sy
        if tol is not None and max(np.abs(sx).max(), np.abs(sy).max()) < tol:
            break
    return px, py, it


def _light_result(p, anchors, r, valid, n_ranges, enough, iterations):
    """Fix, residual and status without covariance (degeneracy from the 2x2 determinant)."""
    dx, dy = p[:, 0, None] - anchors[:, 0], p[:, 1, None] - anchors[:, 1]
    dist = np.maximum(np.hypot(dx, dy), 1e-12)
    ux, uy = dx / dist, dy / dist
    vx, vy = ux * valid, uy * valid
    a, b, c = (vx * ux).sum(1), (vx * uy).sum(1), (vy * uy).sum(1)
    half_tr = (a + c) / 2
    disc = np.sqrt(np.maximum((a - c) ** 2 / 4 + b * b, 0.0))
    status = _status(p, enough, half_tr - disc, half_tr + disc)  # 2x2 eigenvalues in closed form
    good = status == OK
    res = np.where(valid, dist - r, 0.0)
    rms = np.sqrt((res**2).sum(1) / np.maximum(n_ranges, 1))
    nan = np.full((len(p), 2, 2), np.nan)
    return TagFixResult(np.where(good[:, None], p, np.nan), nan, np.full(len(p), np.nan), rms, n_ranges, status,
                        iterations)


def _closed_form(anchors: np.ndarray, r: np.ndarray, iv: np.ndarray, dim: int) -> np.ndarray:
    """Weighted linear least squares in (p, s = ||p||^2), batched over tags."""
    design = np.hstack([-2.0 * anchors, np.ones((len(anchors), 1))])  # (N, dim+1)
    rhs = r**2 - (anchors**2).sum(1)[None, :]  # (T, N)
    # Weight each equation by 1/var(r^2) ~ 1/(4 r^2 sigma^2) (first-order propagation).
    w = iv / np.maximum(4.0 * r**2, 1e-6)
    normal = np.einsum("na,tn,nb->tab", design, w, design)
    normal += 1e-12 * np.eye(dim + 1)
    sol = np.linalg.solve(normal, np.einsum("na,tn->ta", design, w * rhs)[..., None])[..., 0]
    return sol[:, :dim]


def _inverse_variance(base_var, base_iv, u, anchor_covariance, valid):
    if anchor_covariance is None:
        return base_iv
    extra = np.einsum("tai,aij,taj->ta", u, anchor_covariance, u)
    return np.where(valid, 1.0 / (base_var + extra), 0.0)


def track_tags_2d(anchors, previous, ranges_m, range_var_m2, anchor_covariance=None, loss="linear", f_scale=2.0,
                  iterations=2):
    """Warm-started planar Gauss-Newton for tracking: many groups of tags, each group against
    its own anchors (the environments' hot path).

    One compiled loop (``_tracking_kernel``) for one env's tags and for thousands of copies:
    per tag and iteration the 2x2 normal equations A = sum w u u^T, g = sum w u r (unit vectors
    u, residuals r, weights w = 1 / (sigma^2 + u^T C u) times the robust loss's) are summed over
    the anchors and solved in closed form. An anchor covariance C adds
    u^T C u = tr(C)/2 + (c00 - c11)/2 (ux^2 - uy^2) + 2 c01 ux uy to a range's variance.

    Args:
        anchors: (S, N, 2) anchor positions per group.
        previous: (S, M, 2) previous fixes (finite), the starting points.
        ranges_m: (S, M, N) ranges; NaN = missing.
        range_var_m2: variance of one range: a scalar, or one per group ((S,) or (S, 1, 1)).
        anchor_covariance: optional (S, N, 2, 2), folded into each range's variance.
        loss, f_scale, iterations: robust loss (see ``robust``), its scale in sigmas, GN steps.

    Returns:
        (positions (S, M, 2), rms residual (S, M), residuals (S, M, N) fitted minus measured);
        NaN where fewer than 3 ranges, not finite, or (residuals) the range is missing.
    """
    ranges_m = np.ascontiguousarray(ranges_m, dtype=np.float64)
    return track_2d(np.ascontiguousarray(anchors, dtype=np.float64), np.ascontiguousarray(previous, dtype=np.float64),
                    ranges_m, *_kernel_options(range_var_m2, anchor_covariance, loss, f_scale, len(ranges_m)),
                    int(iterations))


_NO_COVARIANCE = np.zeros((0, 0, 2, 2))


@dataclass
class TagStep:
    """One step of tag fixing for S groups of M tags (:func:`fix_tags_2d`)."""

    positions: np.ndarray  # (S, M, 2), NaN = no fix
    rms_m: np.ndarray  # (S, M) RMS range residual, NaN = no fix
    status: np.ndarray  # (S, M) int8: TAG_OK, TAG_AMBIGUOUS, TAG_NO_FIX, TAG_POOR_FIT
    switched: np.ndarray  # (S, M) bool: the fix was replaced by its mirror
    refit: np.ndarray  # (S, M) bool: solved again from the closed form
    tag_residual_m: np.ndarray  # (S,) mean RMS residual of the fixed tags
    anchor_residual_m: np.ndarray  # (S, N) each anchor's mean |residual| over them
    any_fix: np.ndarray  # (S,) bool


def fix_tags_2d(anchors, previous, ranges_m, range_var_m2, predicted_var_m2, calibration_var_m2,
                anchor_covariance=None, loss="linear", f_scale=2.0, iterations=2, restart_residual_m=0.3,
                refit_iterations=10, margin_chi2=10.83, mirror_iterations=3, fit_alpha=1e-3) -> TagStep:
    """Tag fixing of one step for both envs (one env: S = 1; the batched env: S copies), one
    compiled pass (``_tracking_kernel.tag_step_2d``):

    1. track: ``iterations`` Gauss-Newton steps from each tag's last fix (:func:`track_tags_2d`'s
       maths; ranges weighted by 1 / (range variance + the anchor's variance along the line of
       sight), that anchor covariance being its calibration's plus the drift part
       (predicted - calibration variance) / 2 per axis);
    2. restart where a tag has no fix or an RMS residual above ``restart_residual_m`` + 2 x the
       largest predicted anchor std (stale anchors raise every residual; only more than they
       explain suggests a wrong minimum): the weighted closed form refined by
       ``refit_iterations`` steps, kept if it fits better and the ranges fix it in two
       directions (not degenerate);
    3. the mirror check (:func:`check_mirror_2d`, with the range variance plus half the mean
       predicted anchor variance): a fix the ranges reject for its mirror is replaced, one that
       fits as well as its mirror is ``TAG_AMBIGUOUS``;
    4. the fit test (:func:`tag_fit_thresholds`): any other fix whose ranges the anchors cannot
       explain at level ``fit_alpha`` (their chi-square, each range's variance the range
       variance + half the anchor's predicted error variance, beyond the chi-square quantile on
       ranges - 2 dof) is ``TAG_POOR_FIT``: the least-squares position is kept (the best the
       ranges give) but not reported as a plain fix;
    5. the residual statistics of the fixes (:func:`~uwb_env.localization._tracking_kernel.residual_statistics`).

    Shapes: anchors (S, N, 2); previous (S, M, 2) (NaN = no fix yet); ranges_m (S, M, N) (NaN
    = missing); range_var_m2 scalar or (S,); predicted / calibration variances (S, N);
    anchor_covariance (S, N, 2, 2) or None (ranges weighted by the range variance alone).
    """
    ranges_m = np.ascontiguousarray(ranges_m, dtype=np.float64)
    var, cov, use_cov, code, c = _kernel_options(range_var_m2, anchor_covariance, loss, f_scale, len(ranges_m))
    out = tag_step_2d(np.ascontiguousarray(anchors, dtype=np.float64), np.ascontiguousarray(previous, dtype=np.float64),
                      ranges_m, var, np.ascontiguousarray(predicted_var_m2, dtype=np.float64),
                      np.ascontiguousarray(calibration_var_m2, dtype=np.float64), cov, use_cov, code, c,
                      int(iterations), float(restart_residual_m), int(refit_iterations), float(margin_chi2),
                      int(mirror_iterations), tag_fit_thresholds(ranges_m.shape[2], float(fit_alpha)))
    return TagStep(*out)


def tag_fit_rejected(anchors, positions, ranges_m, range_var_m2, predicted_var_m2, fit_alpha=1e-3) -> np.ndarray:
    """The tag fit test of :func:`fix_tags_2d` in any dimension, for one group: (M,) True where
    a fix's ranges have a chi-square (each range's variance ``range_var_m2`` + the anchor's
    ``predicted_var_m2`` / dim) beyond the quantile at 1 - ``fit_alpha`` on ranges - dim dof.
    anchors (N, dim), positions (M, dim) (NaN: not tested), ranges_m (M, N) (NaN = missing)."""
    anchors = np.asarray(anchors, dtype=float)
    dim = anchors.shape[1]
    var = range_var_m2 + np.asarray(predicted_var_m2, dtype=float) / dim
    res = np.linalg.norm(np.asarray(positions, dtype=float)[:, None, :] - anchors[None], axis=-1) - ranges_m
    measured = np.isfinite(ranges_m)
    chi2 = np.where(measured, res * res / var, 0.0).sum(axis=1)
    seen = measured.sum(axis=1)
    table = tag_fit_thresholds(anchors.shape[0], float(fit_alpha))
    with np.errstate(invalid="ignore"):
        return (seen >= dim + 1) & (chi2 > table[np.clip(seen - dim, 0, len(table) - 1)])


@lru_cache(maxsize=64)
def tag_fit_thresholds(n_anchors: int, alpha: float) -> np.ndarray:
    """(n_anchors - 1,) chi-square quantiles at 1 - alpha, index = dof (ranges - 2 in 2D,
    ranges - 3 in 3D; index 0 unused): the tag fit test's thresholds."""
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"fit_alpha={alpha!r}: must be in (0, 1)")
    table = np.full(max(n_anchors - 1, 1), np.inf)
    dof = np.arange(1, len(table))
    table[1:] = chdtri(dof, alpha)
    table.setflags(write=False)
    return table


def _kernel_options(range_var_m2, anchor_covariance, loss, f_scale, groups: int) -> tuple:
    """The tracking kernels' shared arguments: the range variance per group ((S,) floats, from
    a scalar or one per group ((S,) or (S, 1, 1))), the anchor covariance and whether it is
    used, the loss code and its scale."""
    if isinstance(range_var_m2, float | int):
        var = np.full(groups, float(range_var_m2))
    else:
        v = np.asarray(range_var_m2, dtype=np.float64).reshape(-1)
        if v.size not in (1, groups):
            raise ValueError(f"range_var_m2: expected a scalar or {groups} values, got shape {np.shape(range_var_m2)}")
        var = np.full(groups, v[0]) if v.size == 1 else np.ascontiguousarray(v)
    use_cov = anchor_covariance is not None
    cov = np.ascontiguousarray(anchor_covariance, dtype=np.float64) if use_cov else _NO_COVARIANCE
    if loss not in LOSS_CODES:
        check_loss(loss)
    return var, cov, use_cov, LOSS_CODES[loss], float(f_scale)


# Per-tag verdicts of the tracker (``check_mirror_2d``).
TAG_STATUS_NAMES = {TAG_OK: "ok", TAG_AMBIGUOUS: "ambiguous", TAG_NO_FIX: "no_fix", TAG_POOR_FIT: "poor_fit"}


def check_mirror_2d(anchors, positions, ranges_m, range_var_m2, anchor_covariance=None, loss="linear", f_scale=2.0,
                    margin_chi2=10.83, iterations=3):
    """The classic wrong minimum of range-only fixing, checked for every tag of every group.

    A fix and its mirror across the anchors' principal axis give nearly the same ranges when
    the anchors are near-collinear (or the tag is far outside them). The mirror is refined by
    the tracking kernel (only where its raw misfit leaves it a chance) and compared by the
    chi-square of the ranges:

    - the mirror fits better by more than ``margin_chi2``: the ranges reject the current fix,
      which is replaced by the mirror's (the tracker never stays in a rejected minimum);
    - the two fit within the margin and lie clearly apart (3 range stds): ``TAG_AMBIGUOUS``
      (a position the ranges cannot decide, not a confident one);
    - no finite fix: ``TAG_NO_FIX``.

    Args: as :func:`track_tags_2d` (``anchors`` (S, N, 2), ``positions`` (S, M, 2) the fixes,
    ``ranges_m`` (S, M, N), ``range_var_m2`` a scalar or one per group (S,)). ``margin_chi2``:
    chi-square margin (10.83 = 1 dof at 1e-3).
    Returns ``(positions, status, switched)``: positions with rejected fixes replaced, status
    (S, M) int8, switched (S, M) bool.
    """
    positions = np.ascontiguousarray(positions, dtype=np.float64)
    return mirror_check_2d(np.ascontiguousarray(anchors, dtype=np.float64), positions,
                           np.ascontiguousarray(ranges_m, dtype=np.float64),
                           *_kernel_options(range_var_m2, anchor_covariance, loss, f_scale, len(positions)),
                           float(margin_chi2), int(iterations))


def check_mirror_3d(anchors, positions, ranges_m, range_var_m2, anchor_covariance=None, loss="linear", f_scale=2.0,
                    margin_chi2=10.83, iterations=10):
    """:func:`check_mirror_2d` in 3D: the mirror across the anchors' best-fit plane.

    Robots carry their anchors at similar heights, so the anchors are nearly coplanar and a
    fix and its reflection across their plane give nearly the same ranges; with one range
    lost (3 ranges, 3 unknowns) the two fit exactly. The mirror is refined with
    :func:`locate_tags` from the reflected start and compared by chi-square, with the same
    rules (switch when the ranges reject the fix, ``TAG_AMBIGUOUS`` when both fit within
    ``margin_chi2`` and lie clearly apart).

    Args: ``anchors`` (N, 3), ``positions`` (M, 3) the fixes, ``ranges_m`` (M, N), the rest as
    :func:`check_mirror_2d`. Returns ``(positions, status, switched)`` with (M,) status/switched.
    """
    anchors = np.asarray(anchors, dtype=float)
    positions = np.array(positions, dtype=float)
    ranges_m = np.asarray(ranges_m, dtype=float)
    m = positions.shape[0]
    status = np.full(m, TAG_OK, dtype=np.int8)
    switched = np.zeros(m, dtype=bool)
    fixed = np.isfinite(positions).all(-1)
    status[~fixed] = TAG_NO_FIX
    if not fixed.any() or anchors.shape[0] < 3:
        return positions, status, switched
    # per tag, the plane of the anchors it has ranges to (with one range lost, the three left
    # fit a fix and its reflection across their plane exactly)
    valid = np.isfinite(ranges_m)[..., None]
    count = np.maximum(valid.sum(1), 1)
    centre = np.where(valid, anchors[None], 0.0).sum(1) / count  # (M, 3)
    spread = np.where(valid, anchors[None] - centre[:, None], 0.0)
    normal = np.linalg.svd(spread)[2][:, -1]  # least principal direction per tag
    mirror = positions - 2.0 * (((positions - centre) * normal).sum(-1))[:, None] * normal
    sigma = math.sqrt(range_var_m2)

    def chi2(p, r):
        res = np.linalg.norm(p[:, None, :] - anchors[None], axis=-1) - r
        return np.nansum(res * res, -1) / range_var_m2, np.isfinite(res).sum(-1)

    c_fix, n_valid = chi2(np.nan_to_num(positions), ranges_m)
    candidate = fixed & (n_valid >= 3) & (np.linalg.norm(mirror - positions, axis=-1) > 3.0 * sigma)
    if not candidate.any():
        return positions, status, switched
    rows = np.flatnonzero(candidate)
    refined = locate_tags(anchors, ranges_m[rows], sigma, anchor_covariance=anchor_covariance, loss=loss,
                          f_scale=f_scale, initial=mirror[rows], max_iterations=iterations, with_covariance=False)
    c_mir = np.full(m, np.inf)
    mirrored = np.array(positions)
    mirrored[rows] = refined.positions
    ok_rows = rows[refined.ok]
    c_mir[ok_rows] = chi2(mirrored[ok_rows], ranges_m[ok_rows])[0]
    apart = np.linalg.norm(mirrored - positions, axis=-1) > 3.0 * sigma
    ok_mirror = candidate & np.isfinite(c_mir) & apart
    better = ok_mirror & (c_mir < c_fix - margin_chi2)
    tie = ok_mirror & ~better & (np.abs(c_mir - c_fix) <= margin_chi2)
    positions[better] = mirrored[better]
    switched |= better
    status[tie] = TAG_AMBIGUOUS
    return positions, status, switched
