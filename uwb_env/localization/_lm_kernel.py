"""Compiled Levenberg-Marquardt iterations for inter-anchor range problems (numba).

The algorithm is the one documented in ``pair_solver`` (Gauss-Newton first, damping only after
a step that raised the cost, per-pair normal-equation blocks, a step-size stop below the noise);
this module only runs it as one compiled loop. Why compiled: a calibration has a handful to a
few thousand residuals, and in numpy every iteration is a dozen array calls whose overhead is
most of the time for small teams (N = 4: ~90 % of a solve), while at N = 64 the scattered
``bincount`` of the normal equations costs ~1 ms per iteration for arithmetic worth ~50 us.

Status codes: 0 iteration budget spent, 1 converged, 2 no decrease possible, 3 singular
normal equations.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

LOSS_CODES = {"linear": 0, "huber": 1, "soft_l1": 2, "cauchy": 3, "nlos": 4}
MESSAGES = ("max_iterations reached", "converged", "no decrease possible", "singular normal equations")


@njit(cache=True)
def _weight(z, code, c):
    """IRLS weight of a whitened residual (``robust.irls_weights``)."""
    if code == 0:
        return 1.0
    if code == 1:
        a = abs(z)
        return 1.0 if a <= c else c / max(a, 1e-300)
    s = (z / c) ** 2
    if code == 2:
        return 1.0 / math.sqrt(1.0 + s)
    if code == 3:
        return 1.0 / (1.0 + s)
    return 1.0 / (1.0 + s) if z < 0 else 1.0


@njit(cache=True)
def _cost(z, code, c):
    """0.5 * sum rho in scipy's convention (``robust.robust_cost``)."""
    total = 0.0
    if code == 0:
        for v in z:
            total += v * v
        return 0.5 * total
    c2 = c * c
    for v in z:
        t = v * v / c2
        if code == 1:
            total += t if t <= 1.0 else 2.0 * math.sqrt(t) - 1.0
        elif code == 2:
            total += 2.0 * (math.sqrt(1.0 + t) - 1.0)
        elif code == 3:
            total += math.log1p(t)
        else:
            total += math.log1p(t) if v < 0 else t
    return 0.5 * c2 * total


@njit(cache=True)
def _evaluate(x, pi, pj, dist, sqrt_iv, z, u):
    """Whitened residuals z = (||x_i - x_j|| - dist) / sigma and unit vectors u, in place."""
    dim = x.shape[1]
    for p in range(len(pi)):
        i, j = pi[p], pj[p]
        d2 = 0.0
        for a in range(dim):
            t = x[i, a] - x[j, a]
            u[p, a] = t
            d2 += t * t
        d = math.sqrt(d2)
        inv = 1.0 / max(d, 1e-12)
        for a in range(dim):
            u[p, a] *= inv
        z[p] = (d - dist[p]) * sqrt_iv[p]


@njit(cache=True)
def _normal_equations(u, z, sqrt_iv, pi, pj, column, code, c, a_mat, g, scratch):
    """J^T W J and J^T W z from per-pair blocks, in place; the extra (gauge) coordinate's row
    and column are the identity's. ``scratch``: (3, dim) float buffer (no allocation per call)."""
    m = a_mat.shape[0]
    dim = u.shape[1]
    a_mat[:, :] = 0.0
    g[:] = 0.0
    vi = scratch[0]
    for p in range(len(pi)):
        rw = math.sqrt(_weight(z[p], code, c))
        root_w = sqrt_iv[p] * rw
        wz = z[p] * rw
        bi, bj = pi[p] * dim, pj[p] * dim
        for a in range(dim):
            vi[a] = u[p, a] * root_w
        for a in range(dim):
            ca, da = column[bi + a], column[bj + a]
            for b in range(dim):
                cb, db = column[bi + b], column[bj + b]
                o = vi[a] * vi[b]
                a_mat[ca, cb] += o
                a_mat[da, db] += o
                a_mat[ca, db] -= o
                a_mat[da, cb] -= o
            g[ca] += vi[a] * wz
            g[da] -= vi[a] * wz
    for k in range(m):
        a_mat[m - 1, k] = 0.0
        a_mat[k, m - 1] = 0.0
    a_mat[m - 1, m - 1] = 1.0
    g[m - 1] = 0.0


@njit(cache=True)
def _cholesky_solve(mat, rhs, low, out):
    """Solve mat @ out = rhs by Cholesky (lower factor in ``low``); False if not positive definite."""
    m = mat.shape[0]
    for j in range(m):
        s = mat[j, j]
        for k in range(j):
            s -= low[j, k] * low[j, k]
        if not s > 0.0:
            return False
        d = math.sqrt(s)
        low[j, j] = d
        for i in range(j + 1, m):
            s = mat[i, j]
            for k in range(j):
                s -= low[i, k] * low[j, k]
            low[i, j] = s / d
    for i in range(m):
        s = rhs[i]
        for k in range(i):
            s -= low[i, k] * out[k]
        out[i] = s / low[i, i]
    for i in range(m - 1, -1, -1):
        s = out[i]
        for k in range(i + 1, m):
            s -= low[k, i] * out[k]
        out[i] = s / low[i, i]
    return True


@njit(cache=True)
def _work_buffers(npairs, dim, m):
    """Residuals and unit vectors (current and trial), normal equations, Cholesky factor,
    right-hand side, step and scratch of one solve: allocated once, reused every iteration."""
    return (np.empty(npairs), np.empty((npairs, dim)), np.empty(npairs), np.empty((npairs, dim)), np.empty((m, m)),
            np.zeros((m, m)), np.empty(m), np.empty(m), np.empty((3, dim)))


@njit(cache=True)
def lm_pairs(x0, pi, pj, column, n_free, dist, sqrt_iv, code, c, max_iterations, xtol2, ftol):
    """Minimize 0.5 * sum rho(z_p^2) over the free coordinates (``pair_solver.solve_pair_ranges``).

    Returns (x, information, residuals_m, robust_weights, cost, iterations, status)."""
    n, dim = x0.shape
    npairs = len(pi)
    m = n_free + 1
    x = x0.copy()
    trial = np.empty_like(x)
    z, u, z_new, u_new, a_mat, low, g, step, scratch = _work_buffers(npairs, dim, m)
    damped = np.empty((m, m))
    _evaluate(x, pi, pj, dist, sqrt_iv, z, u)
    cost = _cost(z, code, c)
    cost_new = cost
    have_info = False
    lam = 0.0
    status = 0
    it = 0
    for it in range(1, max_iterations + 1):
        _normal_equations(u, z, sqrt_iv, pi, pj, column, code, c, a_mat, g, scratch)
        small_step = False
        while True:
            if lam > 0.0:
                for r in range(m):
                    for q in range(m):
                        damped[r, q] = a_mat[r, q]
                    dg = a_mat[r, r]
                    damped[r, r] += lam * (dg if dg > 0.0 else 1.0)
                ok = _cholesky_solve(damped, g, low, step)
            else:
                ok = _cholesky_solve(a_mat, g, low, step)
            if ok:
                norm2 = 0.0
                for r in range(m):
                    norm2 += step[r] * step[r]
                for k in range(n):
                    for a in range(dim):
                        trial[k, a] = x[k, a] - step[column[k * dim + a]]
                if norm2 <= xtol2:
                    small_step = True
                    break
                _evaluate(trial, pi, pj, dist, sqrt_iv, z_new, u_new)
                cost_new = _cost(z_new, code, c)
                if cost_new <= cost:  # False for NaN
                    break
            lam = max(lam * 10.0, 1e-6)
            if lam > 1e12:
                status = 2 if ok else 3
                break
        if small_step:
            # the last step is taken without a new evaluation: residuals to first order
            for p in range(npairs):
                s = 0.0
                for a in range(dim):
                    s += (step[column[pi[p] * dim + a]] - step[column[pj[p] * dim + a]]) * u[p, a]
                z[p] -= sqrt_iv[p] * s
            x[:, :] = trial
            cost = _cost(z, code, c)
            status = 1
            if code == 0:
                have_info = True  # J^T W J barely moves over a sub-xtol step
            break
        if status != 0:
            break
        small_gain = cost - cost_new <= ftol * max(cost, 1e-300)
        x[:, :] = trial
        z[:] = z_new
        u[:, :] = u_new
        cost = cost_new
        lam = lam / 10.0 if lam > 1e-6 else 0.0
        if small_gain:
            status = 1
            break
    weights = np.empty(npairs)
    for p in range(npairs):
        weights[p] = _weight(z[p], code, c)
    if not have_info:
        _normal_equations(u, z, sqrt_iv, pi, pj, column, code, c, a_mat, g, scratch)
    residuals = z / sqrt_iv
    return x, a_mat, residuals, weights, cost, it, status


@njit(cache=True)
def gauss_newton_teams(x0, pi, pj, dist, sqrt_iv, column, n_free, code, c, max_iterations, xtol_sigma, ok,
                       ftol=1e-12):
    """Undamped Gauss-Newton (IRLS for robust losses) for many teams with the same pairs and
    gauge (``batched_calibration``): x0 (K, n, dim), dist / sqrt_iv (K, P), ok (K,) teams to
    solve. A team whose step raises the cost (where the full solver would damp), whose normal
    equations are singular, or that does not converge within the budget comes back not ok.
    Returns (x, ok)."""
    k_teams, n, dim = x0.shape
    npairs = len(pi)
    m = n_free + 1
    x = x0.copy()
    ok = ok.copy()
    trial = np.empty((n, dim))
    z, u, z_new, u_new, a_mat, low, g, step, scratch = _work_buffers(npairs, dim, m)
    for k in range(k_teams):
        if not ok[k]:
            continue
        xk = x[k]
        xtol = xtol_sigma / np.max(sqrt_iv[k])
        _evaluate(xk, pi, pj, dist[k], sqrt_iv[k], z, u)
        done = False
        for _ in range(max_iterations):
            _normal_equations(u, z, sqrt_iv[k], pi, pj, column, code, c, a_mat, g, scratch)
            if not _cholesky_solve(a_mat, g, low, step):
                ok[k] = False
                done = True
                break
            norm2 = 0.0
            for r in range(m):
                norm2 += step[r] * step[r]
            for q in range(n):
                for a in range(dim):
                    trial[q, a] = xk[q, a] - step[column[q * dim + a]]
            _evaluate(trial, pi, pj, dist[k], sqrt_iv[k], z_new, u_new)
            cost_old = _cost(z, code, c)
            cost_new = _cost(z_new, code, c)
            # converged as the full solver: a step under the tolerance, or (IRLS, which creeps
            # linearly) a relative cost decrease under ftol
            small = math.sqrt(norm2) <= xtol or (cost_new <= cost_old and cost_old - cost_new <= ftol * cost_old)
            worse = cost_new > cost_old * (1 + 1e-12) + 1e-300
            if not worse:
                xk[:, :] = trial
                z[:] = z_new
                u[:, :] = u_new
            elif not small:
                ok[k] = False  # the full solver would damp: hand the team back
            if small or worse:
                done = True
                break
        if not done:
            ok[k] = False
    return x, ok


@njit(cache=True)
def team_covariances(x, pi, pj, dist, sqrt_iv, column, n_free, code, c, rows):
    """(J^T W J)^-1 at each listed team's solution (robust weights included), expanded to all
    n*dim coordinates with zeros on the gauge-fixed ones: (len(rows), n*dim, n*dim), and
    whether each information matrix was positive definite (NaN covariance where not)."""
    k_teams, n, dim = x.shape
    npairs = len(pi)
    m = n_free + 1
    nd = n * dim
    cov = np.zeros((len(rows), nd, nd))
    good = np.ones(len(rows), np.bool_)
    z = np.empty(npairs)
    u = np.empty((npairs, dim))
    a_mat = np.empty((m, m))
    low = np.zeros((m, m))
    g = np.empty(m)
    e = np.zeros(m)
    col = np.empty(m)
    inv = np.empty((m, m))
    scratch = np.empty((3, dim))
    for r in range(len(rows)):
        k = rows[r]
        _evaluate(x[k], pi, pj, dist[k], sqrt_iv[k], z, u)
        _normal_equations(u, z, sqrt_iv[k], pi, pj, column, code, c, a_mat, g, scratch)
        for q in range(m):
            e[:] = 0.0
            e[q] = 1.0
            if not _cholesky_solve(a_mat, e, low, col):
                good[r] = False
                break
            for p in range(m):
                inv[p, q] = col[p]
        if not good[r]:
            cov[r, :, :] = np.nan
            continue
        for a in range(nd):
            ca = column[a]
            if ca == n_free:
                continue
            for b in range(nd):
                cb = column[b]
                if cb != n_free:
                    cov[r, a, b] = inv[ca, cb]
    return cov, good
