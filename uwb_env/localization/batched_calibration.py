"""Later calibrations of many teams at once (the batched env): one Gauss-Newton in numpy.

:func:`calibrate_with_priors` solves what :func:`~uwb_env.localization.calibrate_anchors` solves
for a later calibration (``prior`` given, every pair measured), for K teams of N anchors in a
handful of array calls per iteration: the same gauge (anchor 0 at the origin, the anchor
farthest from it on +x), the same start (the prior in that gauge), the plain least-squares
stage then the robust one, the same stopping rule, the same chi-square fit verdict and the same
rigid alignment onto the prior. A team is handed back (``None``) wherever the full solver would
do more than this one solve: a missing pair, a fit the verdict rejects or a residual beyond
``restart_sigmas`` (the full solver then restarts, unfolds or rejects outliers), a step that
raises the cost, or no convergence. The caller solves those with ``calibrate_anchors``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import chdtrc

from uwb_env.localization.alignment import paper_frame, rigid_align
from uwb_env.localization.robust import irls_weights
from uwb_env.measurements import RangeMatrix


@dataclass
class BatchedCalibration:
    """One team's result, with the fields the envs read from a ``CalibrationResult``."""

    positions: np.ndarray
    covariance: np.ndarray
    residuals_m: np.ndarray
    chi2: float
    dof: int
    status: str = "ok"
    ambiguous: bool = False

    def anchor_covariance(self) -> np.ndarray:
        n, dim = self.positions.shape
        idx = np.arange(n)
        return self.covariance.reshape(n, dim, n, dim)[idx, :, idx, :]

    @property
    def rms_residual_m(self) -> float:
        return float(np.sqrt(np.mean(self.residuals_m**2)))


def calibrate_with_priors(matrices: list[RangeMatrix], priors: np.ndarray, range_std_m: float,
                          loss: str = "huber", f_scale: float = 3.0, gauge: str = "prior",
                          max_iterations: int = 50, fit_alpha: float = 1e-3,
                          restart_sigmas: float = 8.0) -> list[BatchedCalibration | None]:
    """2D later calibrations of K teams; ``priors`` (K, N, 2). See the module docstring."""
    k_teams = len(matrices)
    out: list[BatchedCalibration | None] = [None] * k_teams
    if k_teams == 0:
        return out
    data = [m.complete_symmetric(0.03, range_std_m) for m in matrices]
    full = [i for i, d in enumerate(data) if d is not None]
    if not full:
        return out
    pairs = data[full[0]][0]
    dist = np.stack([data[i][1] for i in full])
    var = np.stack([data[i][2] for i in full])
    prior = priors[full]
    # the gauge of the full solver: anchor 0 at the origin, the anchor farthest from it on +x
    far = np.argmax(np.linalg.norm(prior - prior[:, :1], axis=2), axis=1)
    for b in np.unique(far):
        rows = np.flatnonzero(far == b)
        results = _solve_group(pairs, dist[rows], var[rows], prior[rows], int(b), loss, f_scale, gauge,
                               max_iterations, fit_alpha, restart_sigmas)
        for r, res in zip(rows, results, strict=True):
            out[full[r]] = res
    return out


def _solve_group(pairs, dist, var, prior, b, loss, f_scale, gauge, max_iterations, fit_alpha, restart_sigmas):
    k_teams, n, dim = prior.shape
    free = np.ones((n, dim), dtype=bool)
    free[0] = False
    free[b, 1] = False
    free = free.ravel()
    x = np.stack([p @ rot.T + t for p, (rot, t) in zip(prior, (paper_frame(p, (0, b)) for p in prior),
                                                        strict=True)])
    i, j = pairs[:, 0], pairs[:, 1]
    sqrt_iv = 1.0 / np.sqrt(var)
    ok = np.ones(k_teams, dtype=bool)
    x, ok, _ = _gauss_newton(x, i, j, dist, sqrt_iv, free, "linear", 1.0, max_iterations, 1e-3, ok)
    if loss != "linear":  # the robust stage from the plain solution, 4x the budget (linear convergence)
        x, ok, _ = _gauss_newton(x, i, j, dist, sqrt_iv, free, loss, f_scale, 4 * max_iterations, 1e-4, ok)
    res, u = _residuals(x, i, j, dist)
    z = res * sqrt_iv
    rw = irls_weights(z, loss, f_scale)  # the covariance uses the final robust weights
    chi2 = (z * z).sum(1)
    dof = len(pairs) - int(free.sum())
    p_value = chdtrc(dof, chi2) if dof > 0 else np.ones(k_teams)
    ok &= (p_value >= fit_alpha) & (np.abs(z).max(1) <= restart_sigmas)
    info = _information(u, i, j, (sqrt_iv * np.sqrt(rw)) ** 2, n, dim)[:, free][:, :, free]
    results: list[BatchedCalibration | None] = []
    for k in range(k_teams):
        if not ok[k]:
            results.append(None)
            continue
        try:
            cov_free = np.linalg.inv(info[k])
        except np.linalg.LinAlgError:
            results.append(None)
            continue
        cov = np.zeros((n * dim, n * dim))
        cov[np.ix_(free, free)] = cov_free
        rot, trans = rigid_align(x[k], prior[k], allow_reflection=True, pivot=0 if gauge == "anchor0" else None)
        left = np.matmul(rot, cov.reshape(n, dim, n * dim)).reshape(n * dim, n, dim)
        cov = np.matmul(left, rot.T).reshape(n * dim, n * dim)
        results.append(BatchedCalibration(x[k] @ rot.T + trans, cov, res[k], float(chi2[k]), dof))
    return results


def _residuals(x, i, j, dist):
    diff = x[:, i] - x[:, j]
    d = np.sqrt((diff * diff).sum(-1))
    return d - dist, diff / np.maximum(d, 1e-12)[..., None]


def _incidence(i, j, n):
    e = np.zeros((len(i), n))
    e[np.arange(len(i)), i] = 1.0
    e[np.arange(len(i)), j] = -1.0
    return e


def _information(u, i, j, w, n, dim):
    """J^T W J over all coordinates, (K, n*dim, n*dim): pair p adds w u u^T with the signs of
    its incidence row (+ on i, - on j)."""
    e = _incidence(i, j, n)
    outer = w[..., None, None] * u[..., :, None] * u[..., None, :]  # (K, P, dim, dim)
    info = np.einsum("pa,pb,kpcd->kacbd", e, e, outer)
    return info.reshape(u.shape[0], n * dim, n * dim)


def _gauss_newton(x, i, j, dist, sqrt_iv, free, loss, f_scale, max_iterations, xtol_sigma, ok):
    """Undamped Gauss-Newton (IRLS for robust losses) over the free coordinates of every team;
    a team whose step raises the cost or that does not converge is marked not ok."""
    k_teams, n, dim = x.shape
    x = x.copy()
    xtol = xtol_sigma / sqrt_iv.max(axis=1)
    done = ~ok
    incidence = _incidence(i, j, n)
    res, u = _residuals(x, i, j, dist)
    for _ in range(max_iterations):
        active = ~done
        if not active.any():
            break
        z = res * sqrt_iv
        rw = np.ones_like(z) if loss == "linear" else irls_weights(z, loss, f_scale)
        w = sqrt_iv**2 * rw
        info = _information(u[active], i, j, w[active], n, dim)[:, free][:, :, free]
        g = (w[active] * res[active])[..., None] * u[active]
        grad_full = np.einsum("pa,kpd->kad", incidence, g)
        try:
            step = np.linalg.solve(info, grad_full.reshape(len(grad_full), -1)[:, free][..., None])[..., 0]
        except np.linalg.LinAlgError:
            ok[active] = False
            done[active] = True
            break
        delta = np.zeros((len(step), n * dim))
        delta[:, free] = step
        trial = x[active] - delta.reshape(-1, n, dim)
        res_t, u_t = _residuals(trial, i, j, dist[active])
        cost_old = _cost(res[active] * sqrt_iv[active], loss, f_scale)
        cost_new = _cost(res_t * sqrt_iv[active], loss, f_scale)
        idx = np.flatnonzero(active)
        small = np.sqrt((step * step).sum(1)) <= xtol[active]
        worse = cost_new > cost_old * (1 + 1e-12) + 1e-300
        accept = ~worse
        x[idx[accept]], res[idx[accept]], u[idx[accept]] = trial[accept], res_t[accept], u_t[accept]
        ok[idx[worse & ~small]] = False  # the full solver would damp: hand the team back
        done[idx[small | worse]] = True
    ok &= done  # not converged within the budget: hand back
    return x, ok, rw


def _cost(z, loss, f_scale):
    if loss == "linear":
        return 0.5 * (z * z).sum(-1)
    c2 = f_scale**2
    s = z * z
    if loss == "huber":
        t = s / c2
        rho = np.where(t <= 1.0, t, 2.0 * np.sqrt(t) - 1.0)
    elif loss == "soft_l1":
        rho = 2.0 * (np.sqrt(1.0 + s / c2) - 1.0)
    else:  # cauchy
        rho = np.log1p(s / c2)
    return 0.5 * c2 * rho.sum(-1)
