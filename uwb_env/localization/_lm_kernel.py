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
# Below this reciprocal condition number of J^T W J the free coordinates are not fixed by
# the ranges (collinear / coplanar anchors, too few pairs for a rigid shape).
RCOND_MIN = 1e-10
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
def _cholesky_factor(mat, low):
    """Lower Cholesky factor of ``mat`` into ``low``; False if not positive definite."""
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
    return True


@njit(cache=True)
def _cholesky_substitute(low, rhs, out):
    """Solve (low low^T) out = rhs by forward and back substitution."""
    m = low.shape[0]
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


@njit(cache=True)
def _cholesky_solve(mat, rhs, low, out):
    """Solve mat @ out = rhs by Cholesky (lower factor in ``low``); False if not positive definite."""
    if not _cholesky_factor(mat, low):
        return False
    _cholesky_substitute(low, rhs, out)
    return True


@njit(cache=True)
def _newton_matrix(u, z, dist, sqrt_iv, pi, pj, column, code, c, a_mat, hess, low):
    """hess = J^T W J + sum_p w_p z_p Hess(z_p), the Hessian of the (IRLS-weighted) cost, in
    place, and its Cholesky factor in ``low``; False where it is not positive definite (far
    from a minimum), and the caller steps with J^T W J (Gauss-Newton) instead.

    Why: Gauss-Newton drops the residuals' curvature, (I - u u^T) / d per pair. That is harmless
    where the ranges fix the shape firmly, but along a weakly determined direction (3D anchors
    at similar heights, near-collinear teams) the dropped term is as large as J^T W J's and
    Gauss-Newton creeps linearly (a 64-anchor 3D first calibration: rate 0.965 per iteration,
    ~260 iterations where 200 were allowed). With it the iterations converge quadratically."""
    m = a_mat.shape[0]
    dim = u.shape[1]
    for r in range(m):
        for q in range(m):
            hess[r, q] = a_mat[r, q]
    for p in range(len(pi)):
        d = dist[p] + z[p] / sqrt_iv[p]
        if d <= 1e-12:
            continue
        coef = _weight(z[p], code, c) * z[p] * sqrt_iv[p] / d
        bi, bj = pi[p] * dim, pj[p] * dim
        for a in range(dim):
            ca, da = column[bi + a], column[bj + a]
            for b in range(dim):
                cb, db = column[bi + b], column[bj + b]
                o = coef * ((1.0 if a == b else 0.0) - u[p, a] * u[p, b])
                hess[ca, cb] += o
                hess[da, db] += o
                hess[ca, db] -= o
                hess[da, cb] -= o
    for k in range(m - 1):
        hess[m - 1, k] = 0.0
        hess[k, m - 1] = 0.0
    hess[m - 1, m - 1] = 1.0
    return _cholesky_factor(hess, low)


@njit(cache=True)
def _trial_point(x, step, column, trial):
    """trial = x - step (the step in free coordinates, ``column`` per coordinate; gauge-fixed
    ones read the extra zero entry); returns the squared step norm."""
    m = step.shape[0]
    n, dim = x.shape
    norm2 = 0.0
    for r in range(m):
        norm2 += step[r] * step[r]
    for k in range(n):
        for a in range(dim):
            trial[k, a] = x[k, a] - step[column[k * dim + a]]
    return norm2


@njit(cache=True)
def _work_buffers(npairs, dim, m):
    """Residuals and unit vectors (current and trial), normal equations, Cholesky factor,
    right-hand side, step, scratch and Newton matrix of one solve: allocated once, reused every
    iteration."""
    return (np.empty(npairs), np.empty((npairs, dim)), np.empty(npairs), np.empty((npairs, dim)), np.empty((m, m)),
            np.zeros((m, m)), np.empty(m), np.empty(m), np.empty((3, dim)), np.empty((m, m)))


@njit(cache=True)
def lm_pairs(x0, pi, pj, column, n_free, dist, sqrt_iv, code, c, max_iterations, xtol2, ftol):
    """Minimize 0.5 * sum rho(z_p^2) over the free coordinates (``pair_solver.solve_pair_ranges``).

    Returns (x, information, residuals_m, robust_weights, cost, iterations, status)."""
    n, dim = x0.shape
    npairs = len(pi)
    m = n_free + 1
    x = x0.copy()
    bufs = _work_buffers(npairs, dim, m)
    z, u, _, _, a_mat, _, g, _, scratch, _ = bufs
    cost, it, status, have_info = _lm_iterate(x, pi, pj, column, dist, sqrt_iv, code, c, max_iterations, xtol2, ftol,
                                              bufs, np.empty((m, m)), np.empty_like(x))
    weights = np.empty(npairs)
    for p in range(npairs):
        weights[p] = _weight(z[p], code, c)
    if not have_info:
        _normal_equations(u, z, sqrt_iv, pi, pj, column, code, c, a_mat, g, scratch)
    residuals = z / sqrt_iv
    return x, a_mat, residuals, weights, cost, it, status


@njit(cache=True)
def _lm_iterate(x, pi, pj, column, dist, sqrt_iv, code, c, max_iterations, xtol2, ftol, bufs, damped, trial):
    """The iterations of :func:`lm_pairs` on ``x`` in place, in caller-owned buffers (``bufs``
    from ``_work_buffers``, ``damped`` (m, m), ``trial`` like x): a team solver reuses them
    instead of allocating a dozen small arrays per solve. On return bufs' residuals and unit
    vectors are those at x. Returns (cost, iterations, status, whether bufs' normal equations
    are those at x).

    An undamped iteration first tries the step with the cost's Hessian (``_newton_matrix``)
    where that is positive definite; where it is not, or that step raises the cost, the step is
    Gauss-Newton's (J^T W J), damped (Levenberg-Marquardt) while the cost rises. (Trying the
    Hessian only once Gauss-Newton is seen to converge linearly does not work: its first steps
    can leave the region where the Hessian is positive definite, and then it crawls there.)"""
    npairs = len(pi)
    dim = x.shape[1]
    z, u, z_new, u_new, a_mat, low, g, step, scratch, hess = bufs
    m = a_mat.shape[0]
    _evaluate(x, pi, pj, dist, sqrt_iv, z, u)
    cost = _cost(z, code, c)
    cost_new = cost
    have_info = False
    lam = 0.0
    status = 0
    it = 0
    for it in range(1, max_iterations + 1):
        _normal_equations(u, z, sqrt_iv, pi, pj, column, code, c, a_mat, g, scratch)
        newton = lam == 0.0 and _newton_matrix(u, z, dist, sqrt_iv, pi, pj, column, code, c, a_mat, hess, low)
        small_step = False
        while True:
            if lam > 0.0:
                for r in range(m):
                    for q in range(m):
                        damped[r, q] = a_mat[r, q]
                    dg = a_mat[r, r]
                    damped[r, r] += lam * (dg if dg > 0.0 else 1.0)
                ok = _cholesky_solve(damped, g, low, step)
            elif newton:
                _cholesky_substitute(low, g, step)  # factored by _newton_matrix
                ok = True
            else:
                ok = _cholesky_solve(a_mat, g, low, step)
            if ok:
                norm2 = _trial_point(x, step, column, trial)
                if norm2 <= xtol2:
                    small_step = True
                    break
                _evaluate(trial, pi, pj, dist, sqrt_iv, z_new, u_new)
                cost_new = _cost(z_new, code, c)
                if cost_new <= cost:  # False for NaN
                    break
            if newton:  # the Newton step raised the cost: Gauss-Newton, then damped, as always
                newton = False
                continue
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
    return cost, it, status, have_info


@njit(cache=True)
def _gauss_newton_team(xk, pi, pj, dist, sqrt_iv, column, code, c, max_iterations, xtol_sigma, trial, bufs):
    """Undamped Newton / Gauss-Newton (IRLS for robust losses) of one team in place, the full
    solver's undamped steps; False where the full solver would do more: a step that raises the
    cost (it would damp), singular normal equations, or no convergence within the budget."""
    z, u, z_new, u_new, a_mat, low, g, step, scratch, hess = bufs
    xtol = xtol_sigma / np.max(sqrt_iv)
    _evaluate(xk, pi, pj, dist, sqrt_iv, z, u)
    for _ in range(max_iterations):
        _normal_equations(u, z, sqrt_iv, pi, pj, column, code, c, a_mat, g, scratch)
        newton = _newton_matrix(u, z, dist, sqrt_iv, pi, pj, column, code, c, a_mat, hess, low)
        cost_old = _cost(z, code, c)
        while True:  # the full solver's step: Newton, or Gauss-Newton where Newton raised the cost
            if newton:
                _cholesky_substitute(low, g, step)
            elif not _cholesky_solve(a_mat, g, low, step):
                return False
            norm2 = _trial_point(xk, step, column, trial)
            _evaluate(trial, pi, pj, dist, sqrt_iv, z_new, u_new)
            cost_new = _cost(z_new, code, c)
            # converged as the full solver: a step under the tolerance, or (IRLS, which creeps
            # linearly) a relative cost decrease under ftol (1e-12)
            small = math.sqrt(norm2) <= xtol or (cost_new <= cost_old and cost_old - cost_new <= 1e-12 * cost_old)
            worse = cost_new > cost_old * (1 + 1e-12) + 1e-300
            if not (worse and newton and not small):
                break
            newton = False
        if not worse:
            xk[:, :] = trial
            z[:] = z_new
            u[:, :] = u_new
        if worse:
            return small  # a raised cost is only accepted as a stop under the tolerance
        if small:
            return True
    return False


@njit(cache=True)
def _team_covariance(xk, pi, pj, dist, sqrt_iv, column, code, c, out, bufs, inv, e, col):
    """(J^T W J)^-1 at one team's solution (robust weights included) into ``out`` (n*dim,
    n*dim), zeros on the gauge-fixed coordinates; False (and NaN) where the information matrix
    is not positive definite or its reciprocal condition number is below ``RCOND_MIN`` (the
    full solver's ``PairSolution.covariance`` test, with the same bound on the matrix's 1-norm
    and the inverse's exact 1-norm, so never laxer: a 3-anchor team near a line once passed
    the positive-definite test alone with a 4e36 m^2 covariance, and the next relocation of one
    of its anchors could not invert that prior)."""
    z, u, _, _, a_mat, low, g, _, scratch, _ = bufs
    m = a_mat.shape[0]
    n_free = m - 1
    nd = out.shape[0]
    _evaluate(xk, pi, pj, dist, sqrt_iv, z, u)
    _normal_equations(u, z, sqrt_iv, pi, pj, column, code, c, a_mat, g, scratch)
    if not _cholesky_factor(a_mat, low):  # factored once, one substitution per column
        out[:, :] = np.nan
        return False
    inv_norm = 0.0
    for q in range(m):
        e[:] = 0.0
        e[q] = 1.0
        _cholesky_substitute(low, e, col)
        column_sum = 0.0
        for p in range(m):
            inv[p, q] = col[p]
            column_sum += abs(col[p])
        inv_norm = max(inv_norm, column_sum)
    trace = 0.0
    for q in range(m):
        trace += a_mat[q, q]
    if not 1.0 / (trace * math.sqrt(m) * inv_norm) > RCOND_MIN:
        out[:, :] = np.nan
        return False
    out[:, :] = 0.0
    for a in range(nd):
        ca = column[a]
        if ca == n_free:
            continue
        for b in range(nd):
            cb = column[b]
            if cb != n_free:
                out[a, b] = inv[ca, cb]
    return True


@njit(cache=True)
def _lm_team(xk, pi, pj, dist, sqrt_iv, column, code, c, max_iterations, bufs, damped, trial):
    """One team as the full solver's ``_Problem.solve`` does it (``pair_solver.solve_pair_ranges``
    twice: the plain stage, 1e-3 sigma step tolerance, then for a robust ``code`` the robust
    stage from there, 4x the budget, 1e-4 sigma), in place, in the caller's buffers
    (``_lm_iterate``); True where the last stage converged."""
    top = 0.0
    far = 0.0
    for p in range(len(dist)):
        top = max(top, sqrt_iv[p])
        far = max(far, abs(dist[p]))
    floor = 1e-12 * far
    xtol = max(1e-3 / top, floor)
    _, _, status, _ = _lm_iterate(xk, pi, pj, column, dist, sqrt_iv, 0, 1.0, max_iterations, xtol * xtol, 1e-12,
                                  bufs, damped, trial)
    if code != 0:
        xtol = max(1e-4 / top, floor)
        _, _, status, _ = _lm_iterate(xk, pi, pj, column, dist, sqrt_iv, code, c, 4 * max_iterations, xtol * xtol,
                                      1e-12, bufs, damped, trial)
    return status == 1


@njit(cache=True)
def solve_teams_2d(start, ref, pi, pj, dist, sqrt_iv, code, c, max_iterations, damped=False):
    """Many 2D teams with the same pairs in one compiled loop (``batched_calibration``).

    Team k is put in the paper frame of ``start[k]`` about anchors (0, ``ref[k]``) (anchor 0
    at the origin, anchor ref on +x, the others' y summing positive; not ok where
    ``alignment.paper_frame`` would raise), solved by Gauss-Newton with the linear loss
    (``max_iterations``, step tolerance 1e-3 sigma), then, for a robust ``code``, by IRLS from
    there (4x the budget, 1e-4 sigma). start (K, n, 2), ref (K,), dist / sqrt_iv (K, P).
    Undamped (default): a team whose step raises the cost is not ok (the full solver would
    damp); ``damped``: Levenberg-Marquardt, the full solver's own iterations (``_lm_team``).

    Returns (x (K, n, 2) in the frame, ok (K,), residuals_m (K, P), chi2 (K,), max |z| (K,),
    robust cost (K,), covariance (K, 2n, 2n) in the frame with zeros on the fixed
    coordinates, NaN where the information matrix is singular, good (K,) its positive
    definiteness). Only rows where ok are meaningful: elsewhere x is uninitialized or a partial
    iterate."""
    k_teams, n, dim = start.shape
    npairs = len(pi)
    nd = n * dim
    m = nd - 3 + 1
    x = np.empty_like(start)
    ok = np.zeros(k_teams, np.bool_)
    res = np.full((k_teams, npairs), np.nan)
    chi2 = np.full(k_teams, np.nan)
    zmax = np.full(k_teams, np.nan)
    cost = np.full(k_teams, np.nan)
    cov = np.full((k_teams, nd, nd), np.nan)
    good = np.zeros(k_teams, np.bool_)
    bufs = _work_buffers(npairs, dim, m)
    z = bufs[0]
    trial = np.empty((n, dim))
    damped_buf = np.empty((m, m))
    column = np.empty(nd, np.int64)
    inv = np.empty((m, m))
    e = np.zeros(m)
    col = np.empty(m)
    for k in range(k_teams):
        b = ref[k]
        # the free coordinates: all but anchor 0's and anchor b's y (the extra last column)
        q = 0
        for a in range(nd):
            if a < 2 or a == 2 * b + 1:
                column[a] = m - 1
            else:
                column[a] = q
                q += 1
        # the paper frame (``alignment.paper_frame`` with refs (0, b); not ok where it would raise)
        scale = 1e-12
        for i in range(n):
            for a in range(dim):
                scale = max(scale, abs(start[k, i, a] - start[k, 0, a]))
        ex0 = start[k, b, 0] - start[k, 0, 0]
        ex1 = start[k, b, 1] - start[k, 0, 1]
        norm = math.sqrt(ex0 * ex0 + ex1 * ex1)
        if not norm >= 1e-9 * scale:
            continue
        ex0 /= norm
        ex1 /= norm
        ysum = 0.0
        yabs = 0.0
        for i in range(n):
            y = -(start[k, i, 0] - start[k, 0, 0]) * ex1 + (start[k, i, 1] - start[k, 0, 1]) * ex0
            ysum += y
            yabs = max(yabs, abs(y))
        if not yabs >= 1e-6 * scale:
            continue
        sign = -1.0 if ysum < 0 else 1.0
        xk = x[k]
        for i in range(n):
            r0 = start[k, i, 0] - start[k, 0, 0]
            r1 = start[k, i, 1] - start[k, 0, 1]
            xk[i, 0] = r0 * ex0 + r1 * ex1
            xk[i, 1] = sign * (-r0 * ex1 + r1 * ex0)
        if damped:
            if not _lm_team(xk, pi, pj, dist[k], sqrt_iv[k], column, code, c, max_iterations, bufs, damped_buf,
                            trial):
                continue
        else:
            if not _gauss_newton_team(xk, pi, pj, dist[k], sqrt_iv[k], column, 0, 1.0, max_iterations, 1e-3, trial,
                                      bufs):
                continue
            if code != 0 and not _gauss_newton_team(xk, pi, pj, dist[k], sqrt_iv[k], column, code, c,
                                                    4 * max_iterations, 1e-4, trial, bufs):
                continue
        ok[k] = True
        _evaluate(xk, pi, pj, dist[k], sqrt_iv[k], z, bufs[1])
        total = 0.0
        top = 0.0
        for p in range(npairs):
            res[k, p] = z[p] / sqrt_iv[k, p]
            total += z[p] * z[p]
            top = max(top, abs(z[p]))
        chi2[k] = total
        zmax[k] = top
        cost[k] = _cost(z, code, c)
        good[k] = _team_covariance(xk, pi, pj, dist[k], sqrt_iv[k], column, code, c, cov[k], bufs, inv, e, col)
    return x, ok, res, chi2, zmax, cost, cov, good
