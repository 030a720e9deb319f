"""Robust losses as iteratively-reweighted least-squares weights.

For a whitened residual z = r / sigma and scale c (``f_scale``), each loss rho gives the IRLS
weight w(z) = rho'(s) with s = (z / c)^2, matching ``scipy.optimize.least_squares``'s losses:

- ``linear``:  w = 1
- ``huber``:   w = 1 if |z| <= c else c / |z|
- ``soft_l1``: w = 1 / sqrt(1 + s)
- ``cauchy``:  w = 1 / (1 + s)
- ``nlos``:    one-sided Cauchy: w = 1 for z >= 0, 1 / (1 + s) for z < 0. Residuals are
  model - measured; NLOS only ever lengthens a range (z < 0), so a range *shorter* than the
  model is never down-weighted.
"""

from __future__ import annotations

import numpy as np

LOSSES = ("linear", "huber", "soft_l1", "cauchy", "nlos")


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
    if loss == "nlos":
        return np.where(z < 0, 1.0 / (1.0 + s), 1.0)
    raise ValueError(f"loss={loss!r}: must be one of {LOSSES}")


def robust_cost(z: np.ndarray, loss: str, f_scale: float, axis=None):
    """0.5 * sum rho(z^2) in scipy's convention (rho(s) ~ s near 0): a float, or summed over
    ``axis`` (e.g. -1 for many problems at once)."""
    c2 = f_scale**2
    s = z * z
    if loss == "linear":
        total = s.sum(axis)
        return 0.5 * float(total) if axis is None else 0.5 * total
    t = s / c2
    if loss == "huber":
        rho = np.where(t <= 1.0, t, 2.0 * np.sqrt(t) - 1.0)
    elif loss == "soft_l1":
        rho = 2.0 * (np.sqrt(1.0 + t) - 1.0)
    elif loss == "nlos":
        rho = np.where(z < 0, np.log1p(t), t)
    elif loss == "cauchy":
        rho = np.log1p(t)
    else:
        raise ValueError(f"loss={loss!r}: must be one of {LOSSES}")
    total = rho.sum(axis)
    return 0.5 * c2 * float(total) if axis is None else 0.5 * c2 * total
