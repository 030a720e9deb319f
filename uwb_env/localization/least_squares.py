"""A small dense Levenberg-Marquardt with IRLS robust losses, fast for the problem sizes here.

scipy's ``least_squares`` is general but spends most of its time in Python bookkeeping for
problems with a handful of unknowns; this loop does a few numpy calls per iteration.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from uwb_env.localization.robust import irls_weights, robust_cost


@dataclass
class LMOutcome:
    theta: np.ndarray
    information: np.ndarray  # J^T W J at the solution (W includes robust weights)
    residuals: np.ndarray
    weights: np.ndarray  # final per-residual weights (1/var * robust weight)
    cost: float
    iterations: int
    converged: bool
    message: str


def levenberg_marquardt(
    residual_and_jacobian: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
    theta0: np.ndarray,
    inv_var: np.ndarray,
    loss: str = "linear",
    f_scale: float = 1.0,
    max_iterations: int = 50,
    xtol: float = 1e-10,
    ftol: float = 1e-12,
) -> LMOutcome:
    """Minimize 0.5 * sum rho((r_k / sigma_k)^2) over theta.

    Args:
        residual_and_jacobian: theta -> (r (m,), J (m, p)).
        theta0: starting point (p,).
        inv_var: 1 / sigma_k^2 per residual.
        loss, f_scale: robust loss and its scale in whitened units (see ``robust``).
    """
    theta = np.array(theta0, dtype=float)
    sqrt_iv = np.sqrt(inv_var)
    r, jac = residual_and_jacobian(theta)
    cost = robust_cost(r * sqrt_iv, loss, f_scale)
    lam = 1e-3
    converged, message, it = False, "max_iterations reached", 0
    for it in range(1, max_iterations + 1):
        w = inv_var * irls_weights(r * sqrt_iv, loss, f_scale)
        jw = jac * w[:, None]
        a = jw.T @ jac
        g = jw.T @ r
        diag = np.diag(a).copy()
        diag[diag <= 0] = 1.0
        while True:
            try:
                step = -np.linalg.solve(a + lam * np.diag(diag), g)
            except np.linalg.LinAlgError:
                lam *= 10.0
                if lam > 1e12:
                    message = "singular normal equations"
                    break
                continue
            trial = theta + step
            r_new, jac_new = residual_and_jacobian(trial)
            cost_new = robust_cost(r_new * sqrt_iv, loss, f_scale)
            if np.isfinite(cost_new) and cost_new <= cost:
                break
            lam *= 10.0
            if lam > 1e12:
                message = "no decrease possible"
                step = np.zeros_like(theta)
                trial, r_new, jac_new, cost_new = theta, r, jac, cost
                break
        small_step = np.linalg.norm(step) <= xtol * (np.linalg.norm(theta) + xtol)
        small_gain = cost - cost_new <= ftol * max(cost, 1e-300)
        theta, r, jac, cost = trial, r_new, jac_new, cost_new
        lam = max(lam / 10.0, 1e-12)
        if small_step or small_gain or message != "max_iterations reached":
            converged = message == "max_iterations reached"
            message = "converged" if converged else message
            break
    w = inv_var * irls_weights(r * sqrt_iv, loss, f_scale)
    info = (jac * w[:, None]).T @ jac
    return LMOutcome(theta, info, r, w, cost, it, converged, message)
