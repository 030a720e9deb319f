"""Robust losses as iteratively-reweighted least-squares weights.

For a whitened residual z = r / sigma and scale c (``f_scale``), each loss rho gives the IRLS
weight w(z) = rho'(s) with s = (z / c)^2, matching ``scipy.optimize.least_squares``'s losses:

- ``linear``:  w = 1
- ``huber``:   w = 1 if |z| <= c else c / |z|
- ``soft_l1``: w = 1 / sqrt(1 + s)
- ``cauchy``:  w = 1 / (1 + s)
"""

from __future__ import annotations

import numpy as np

LOSSES = ("linear", "huber", "soft_l1", "cauchy")


def check_loss(loss: str) -> None:
    if loss not in LOSSES:
        raise ValueError(f"loss={loss!r}: must be one of {LOSSES}")


def irls_weights(z: np.ndarray, loss: str, f_scale: float) -> np.ndarray:
    if loss == "linear":
        return np.ones_like(z)
    if loss == "huber":  # 1 / sqrt(s) = c / |z| beyond the scale
        return np.minimum(1.0, f_scale / np.maximum(np.abs(z), 1e-300))
    s = (z / f_scale) ** 2
    if loss == "soft_l1":
        return 1.0 / np.sqrt(1.0 + s)
    if loss == "cauchy":
        return 1.0 / (1.0 + s)
    raise ValueError(f"loss={loss!r}: must be one of {LOSSES}")


def robust_cost(z: np.ndarray, loss: str, f_scale: float) -> float:
    """0.5 * sum rho(z^2) in scipy's convention (rho(s) ~ s near 0)."""
    c2 = f_scale**2
    s = z * z
    if loss == "linear":
        return 0.5 * float(s.sum())
    t = s / c2
    if loss == "huber":
        rho = np.where(t <= 1.0, t, 2.0 * np.sqrt(t) - 1.0)
    elif loss == "soft_l1":
        rho = 2.0 * (np.sqrt(1.0 + t) - 1.0)
    else:
        rho = np.log1p(t)
    return 0.5 * c2 * float(rho.sum())
