"""Per-anchor round: one anchor re-locates against the others (role switching on stock PANS).

Instead of a team round (every anchor ranges to every other: the whole channel for ~1 s), one
anchor ranges to the others, K exchanges each, and solves for its own position with the
others' current estimates held as known *up to their covariance*, plus its own odometry
prediction as a prior. This is what a stock-PANS deployment does when it switches one anchor
to tag mode for a moment (``../shared/reference/dwm1001-field-behaviour.md``), and what a
scheduler can spend channel time on when only one anchor went stale.

Model (navlie style, :class:`RelocationModel`): residuals

    e_j = (||p - a_j|| - r_j) / s_j,   s_j^2 = var(r_j) + u_j^T Sigma_j u_j

(the others' position covariance Sigma_j projected on the line of sight u_j), and the prior
term L (p - p_prior) with L^T L = Sigma_prior^-1. Gauss-Newton with the analytic Jacobian from
several starts: the prior, the linearized multilateration of the ranges, the prior's mirror
across the others' principal axis (plane in 3D), then the answer's own mirror (and, for an
answer on that axis, two starts just off it: a start on it stays there). Another converged
minimum that the ranges resolve from the answer (more than 3 range stds away) and whose total
cost is within the margin makes the result ``ambiguous``: with three others in 3D both
intersections fit the ranges exactly, and only the prior can pick a side. Residuals the noise
cannot explain make it ``poor_fit``. Neither is reported as success.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import chdtrc, chdtri

from uwb_env.localization.errors import GeometryError, InvalidRangeError, SolverArgumentError, TooFewAnchorsError
from uwb_env.measurements import negative_range_floor_m

STATUSES = ("ok", "ambiguous", "poor_fit", "not_converged")


class RelocationModel:
    """Ranges from one point to known anchors: h_j(p) = ||p - a_j||; Jacobian rows u_j^T."""

    def __init__(self, anchors: np.ndarray):
        self.anchors = np.asarray(anchors, dtype=float)

    def evaluate(self, p: np.ndarray) -> np.ndarray:
        diff = p[None, :] - self.anchors
        return np.sqrt((diff * diff).sum(1))

    def jacobian(self, p: np.ndarray) -> np.ndarray:
        diff = p[None, :] - self.anchors
        return diff / np.maximum(np.sqrt((diff * diff).sum(1)), 1e-12)[:, None]

    def jacobian_fd(self, p: np.ndarray, step: float = 1e-6) -> np.ndarray:
        cols = []
        for k in range(len(p)):
            dp = np.zeros_like(p)
            dp[k] = step
            cols.append((self.evaluate(p + dp) - self.evaluate(p - dp)) / (2 * step))
        return np.stack(cols, axis=1)


@dataclass
class RelocationResult:
    """One anchor's new position from its ranges to the others.

    Attributes:
        position: (dim,) estimate; covariance: (dim, dim) (ranges, others' covariance, prior).
        residuals_m: (k,) fitted minus measured range per other anchor used.
        chi2, dof, fit_p_value: goodness of fit of the range residuals (dof = ranges - dim,
            the prior counted as information, not as data to test).
        status: ``ok``, ``ambiguous`` (a clearly different position fits as well and the prior
            cannot decide), ``poor_fit`` or ``not_converged``.
        alternative: (dim,) the competing position when ambiguous, else None.
        iterations: Gauss-Newton iterations of the chosen start.
    """

    position: np.ndarray
    covariance: np.ndarray
    residuals_m: np.ndarray
    chi2: float
    dof: int
    fit_p_value: float
    status: str
    alternative: np.ndarray | None
    iterations: int

    @property
    def ok(self) -> bool:
        return self.status == "ok"


def relocate_anchor(
    ranges_m: np.ndarray,
    others: np.ndarray,
    range_var_m2: float | np.ndarray,
    *,
    others_covariance: np.ndarray | None = None,
    prior: np.ndarray | None = None,
    prior_covariance: np.ndarray | None = None,
    max_iterations: int = 50,
    fit_alpha: float = 1e-3,
) -> RelocationResult:
    """Solve one anchor's position from its ranges to the other anchors.

    Args:
        ranges_m: (k,) bias-corrected ranges (mean of the K exchanges) to ``others``; NaN = none.
        others: (k, dim) the other anchors' current estimates.
        range_var_m2: scalar or (k,) variance of each range (sigma^2 / K for a mean of K).
        others_covariance: optional (k, dim, dim) covariance of the others' estimates.
        prior: optional (dim,) the anchor's own prediction (odometry); ``prior_covariance``
            (dim, dim) its covariance (required with a prior).
        max_iterations: Gauss-Newton iterations per start (near the others' line or plane the
            undamped steps can take 20-25 to settle).
        fit_alpha: significance of the chi-square fit test and of the ambiguity margin.

    Raises:
        InvalidRangeError, TooFewAnchorsError, GeometryError (LocalizationError);
        SolverArgumentError for arguments out of their domain.
    """
    others = np.asarray(others, dtype=float)
    ranges = np.asarray(ranges_m, dtype=float)
    if others.ndim != 2 or others.shape[1] not in (2, 3):
        raise SolverArgumentError(f"others: expected (k, 2) or (k, 3) positions, got shape {others.shape}")
    k, dim = others.shape
    if ranges.shape != (k,):
        raise InvalidRangeError(f"ranges_m: expected shape ({k},), got {ranges.shape}")
    if not np.isfinite(others).all():
        raise SolverArgumentError("others: anchor positions must be finite")
    var = np.broadcast_to(np.asarray(range_var_m2, dtype=float), (k,)).copy()
    if not np.all(np.isfinite(var) & (var > 0)):
        raise SolverArgumentError(f"range_var_m2={range_var_m2!r}: must be finite and > 0")
    # below zero by the tolerance plus the range's own error (a range carried to the round's
    # midpoint carries that error in its variance) is a measurement, as in calibrate_anchors
    floor = negative_range_floor_m(var)
    if np.isinf(ranges).any() or (ranges < floor).any():
        j = int(np.flatnonzero(np.isinf(ranges) | (ranges < floor))[0])
        raise InvalidRangeError(f"ranges_m[{j}] = {ranges[j]!r}: not a corrected range (below {floor[j]:.3g} m)")
    if not (isinstance(max_iterations, int) and max_iterations >= 1):
        raise SolverArgumentError(f"max_iterations={max_iterations!r}: must be an integer >= 1")
    if not 0 < fit_alpha < 1:
        raise SolverArgumentError(f"fit_alpha={fit_alpha!r}: must be in (0, 1)")
    if (prior is None) != (prior_covariance is None):
        raise SolverArgumentError("prior and prior_covariance go together")
    info_prior = None
    if prior is not None:
        prior = np.asarray(prior, dtype=float)
        prior_covariance = np.asarray(prior_covariance, dtype=float)
        if prior.shape != (dim,) or not np.isfinite(prior).all():
            raise SolverArgumentError(f"prior: expected finite ({dim},), got {prior!r}")
        if prior_covariance.shape != (dim, dim) or not np.all(np.linalg.eigvalsh(prior_covariance) > 0):
            raise SolverArgumentError("prior_covariance: expected a positive definite (dim, dim) matrix")
        info_prior = np.linalg.inv(prior_covariance)
    if others_covariance is not None:
        others_covariance = np.asarray(others_covariance, dtype=float)
        if others_covariance.shape != (k, dim, dim) or not np.isfinite(others_covariance).all():
            raise SolverArgumentError(f"others_covariance: expected finite ({k}, {dim}, {dim})")
    keep = np.isfinite(ranges)
    if keep.sum() < (dim if prior is not None else dim + 1):
        raise TooFewAnchorsError(f"{int(keep.sum())} ranges: too few to locate an anchor in {dim}D")
    anchors, ranges, var = others[keep], ranges[keep], var[keep]
    cov_others = None if others_covariance is None else others_covariance[keep]
    model = RelocationModel(anchors)

    def solve(start):
        p = start.copy()
        it, done = 0, False
        for it in range(1, max_iterations + 1):
            u = model.jacobian(p)
            s2 = var if cov_others is None else var + np.einsum("ki,kij,kj->k", u, cov_others, u)
            r = model.evaluate(p) - ranges
            a = (u / s2[:, None]).T @ u
            g = (u / s2[:, None]).T @ r
            if info_prior is not None:
                a = a + info_prior
                g = g + info_prior @ (p - prior)
            try:
                step = np.linalg.solve(a, g)
            except np.linalg.LinAlgError:
                return p, np.inf, None, s2, it, False
            p = p - step
            if float(step @ step) < 1e-16:
                done = True  # (on the last iteration too)
                break
        u = model.jacobian(p)
        s2 = var if cov_others is None else var + np.einsum("ki,kij,kj->k", u, cov_others, u)
        r = model.evaluate(p) - ranges
        chi2 = float(r @ (r / s2))
        total = chi2 + (0.0 if info_prior is None else float((p - prior) @ info_prior @ (p - prior)))
        a = (u / s2[:, None]).T @ u + (0 if info_prior is None else info_prior)
        return p, total, a, s2, it, done

    starts = []
    if prior is not None:
        starts.append(prior)
    linear = _linearized(anchors, ranges)
    if linear is not None:
        starts.append(linear)
    base = starts[0] if starts else anchors.mean(0) + 0.1
    mirror = _mirror(base, anchors)
    if mirror is not None:
        starts.append(mirror)
    if not starts:
        raise GeometryError("no start: the other anchors do not fix a position")
    solutions = [solve(s) for s in starts]
    finite = [s for s in solutions if s[2] is not None and np.isfinite(s[1])]
    if not finite:
        raise GeometryError("degenerate geometry: the ranges and the prior do not fix the position")
    best = min(finite, key=lambda s: s[1])
    # The answer's own mirror (the prior's mirror lands in the answer's basin when the prior lies
    # near the others' line or plane: the other intersection was never tried). An answer on that
    # line (plane) is its own mirror and may be the saddle between the two intersections (a start
    # on it stays on it, by symmetry): then it is also nudged off both ways.
    extra = []
    plane = _principal(anchors)
    if plane is not None:
        centre, normal = plane
        off = float((best[0] - centre) @ normal)
        nudge = 3.0 * float(np.sqrt(var.max()))
        extra.append(best[0] - 2.0 * off * normal)
        if abs(off) < nudge:
            extra += [best[0] + (nudge - off) * normal, best[0] - (nudge + off) * normal]
    for start in extra:
        other = solve(start)
        if other[2] is not None and np.isfinite(other[1]):
            finite.append(other)
    best = min(finite, key=lambda s: s[1])
    if not best[5]:  # a start that stopped short at the same point as a converged one, lower by rounding
        twins = [s for s in finite if s[5] and np.linalg.norm(s[0] - best[0]) < 1e-6]
        best = min(twins, key=lambda s: s[1]) if twins else best
    p, total, a, s2, iterations, converged = best
    try:
        cov = np.linalg.inv(a)
    except np.linalg.LinAlgError:
        raise GeometryError("degenerate geometry: the ranges and the prior do not fix the position") from None
    if not np.all(np.linalg.eigvalsh(cov) > 0) or np.linalg.cond(a) > 1e12:
        raise GeometryError("degenerate geometry: the ranges and the prior do not fix the position")
    r = model.evaluate(p) - ranges
    chi2 = float(r @ (r / s2))
    dof = len(ranges) - dim
    p_value = float(chdtrc(dof, chi2)) if dof > 0 else 1.0
    # an alternative: another converged minimum whose total cost is within the margin. Another
    # minimum is one the ranges resolve from the answer (farther than 3 of their stds), not one
    # outside the answer's covariance: with no redundant range and a vague prior (a near-flat 3D
    # team's heights) both intersections lie inside that covariance, 1.4 m apart.
    margin = float(chdtri(1, fit_alpha))
    resolved = 3.0 * float(np.sqrt(s2.max()))
    # The best such competitor: a start on the plane itself stays there (the saddle between the
    # two intersections, by symmetry), and the other intersection fits better than it.
    rivals = [(tot, q) for q, tot, _, _, _, q_converged in finite
              if q_converged and np.linalg.norm(q - p) > max(resolved, 1e-3) and tot - total <= margin]
    alternative = min(rivals, key=lambda t: t[0])[1] if rivals else None
    if not converged:
        status = "not_converged"
    elif alternative is not None:
        status = "ambiguous"
    elif dof > 0 and p_value < fit_alpha:
        status = "poor_fit"
    else:
        status = "ok"
    return RelocationResult(p, cov, r, chi2, dof, p_value, status, alternative, iterations)


def _linearized(anchors: np.ndarray, ranges: np.ndarray) -> np.ndarray | None:
    """Closed-form start: subtract the first range equation from the others (needs dim + 1)."""
    k, dim = anchors.shape
    if k < dim + 1:
        return None
    a = 2.0 * (anchors[1:] - anchors[0])
    b = ranges[0] ** 2 - ranges[1:] ** 2 + (anchors[1:] ** 2).sum(1) - (anchors[0] ** 2).sum()
    sol, _, rank, _ = np.linalg.lstsq(a, b, rcond=None)
    return sol if rank == dim else None


def _principal(anchors: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Centre and unit normal of the anchors' principal line (2D) / plane (3D), or None."""
    if len(anchors) < 2:
        return None
    centre = anchors.mean(0)
    _, _, vt = np.linalg.svd(anchors - centre)
    return centre, vt[-1]


def _mirror(p: np.ndarray, anchors: np.ndarray) -> np.ndarray | None:
    """p reflected across the anchors' principal line (2D) / plane (3D): the classic mirror minimum
    of near-collinear (near-coplanar) anchors."""
    plane = _principal(anchors)
    if plane is None:
        return None
    centre, normal = plane
    return p - 2.0 * ((p - centre) @ normal) * normal
