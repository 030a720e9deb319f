"""On-board odometry: how each anchor's position estimate drifts between calibrations.

Both models turn the true displacement of a step into the displacement the robot *believes*
it made; the world adds that to the on-board estimate.
"""

from __future__ import annotations

import numpy as np

from uwb_env.config import OdometryConfig
from uwb_env.sim.ranging import upper_tail_threshold


class OdometryModel:
    """Per-robot odometry errors; per-robot parameters are drawn at :meth:`reset`.

    Args:
        config: odometry configuration (``uniform`` paper model or ``distance`` model).
    """

    def __init__(self, config: OdometryConfig):
        self.config = config
        self._uniform = config.model == "uniform"

    def reset(self, n: int, rng: np.random.Generator) -> None:
        cfg = self.config
        self.scale = 1.0 + cfg.scale_error_std * rng.standard_normal(n)
        self.yaw_error_rad = np.zeros(n)
        self.slip_left_s = np.zeros(n)
        self._slip_dt_s, self._slip_q = -1.0, np.inf
        self._any_slip = False
        self._yaw_var_per_m = cfg.yaw_noise_std_rad_per_sqrt_m**2
        self._yaw_var_per_rad = cfg.yaw_noise_std_rad_per_rad**2

    def estimated_displacement(
        self, delta: np.ndarray, turn_rad: np.ndarray, dt_s: float, rng: np.random.Generator
    ) -> np.ndarray:
        """Displacement the robots believe they made, given the true ``delta`` (n, dim)."""
        cfg = self.config
        n, dim = delta.shape
        if self._uniform:
            # Paper: U(-e, e) added to every axis of the estimate every step.
            e = cfg.uniform_error_m
            return delta + rng.uniform(-e, e, (n, dim))
        # 4n normals: [0, 2n) complex white noise, [2n, 3n) yaw increments, [3n, 4n) slip starts.
        noise = rng.standard_normal(4 * n)
        gain = None  # per-robot noise multiplier while slipping; None: nobody slips
        if cfg.slip_rate_per_s > 0.0:
            if dt_s != self._slip_dt_s:  # the threshold depends on dt only: compute it once
                self._slip_dt_s, self._slip_q = dt_s, upper_tail_threshold(cfg.slip_rate_per_s * dt_s)
            start = noise[3 * n :] > self._slip_q
            # Slips are rare: skip the per-robot bookkeeping while nobody slips or starts to.
            if self._any_slip or start.any():
                slipping = self.slip_left_s > 0.0
                self.slip_left_s = np.maximum(self.slip_left_s - dt_s, 0.0)
                self.slip_left_s = np.where(start & ~slipping, cfg.slip_duration_s, self.slip_left_s)
                self._any_slip = bool((self.slip_left_s > 0.0).any())
                gain = np.where(slipping, cfg.slip_noise_multiplier, 1.0)
        d = (delta if dim == 2 else np.ascontiguousarray(delta[:, :2])).view(np.complex128)[:, 0]
        dist = np.abs(d)
        # yaw error random-walks with distance travelled and with turning
        yaw_var = self._yaw_var_per_m * dist + self._yaw_var_per_rad * turn_rad
        yaw_step = np.sqrt(yaw_var) * noise[2 * n : 3 * n]
        self.yaw_error_rad = self.yaw_error_rad + (yaw_step if gain is None else gain * yaw_step)
        white = (cfg.noise_std_m_per_sqrt_m if gain is None else gain * cfg.noise_std_m_per_sqrt_m) * np.sqrt(dist)
        est = self.scale * np.exp(1j * self.yaw_error_rad) * d + white * noise[: 2 * n].view(np.complex128)
        planar = est.view(np.float64).reshape(n, 2)
        if dim == 2:
            return planar
        out = delta.copy()  # the vertical part is integrated without error
        out[:, :2] = planar
        return out

    def expected_error_var_m2(self, distance_m: np.ndarray, steps: np.ndarray, dim: int = 2) -> np.ndarray:
        """Nominal variance (summed over axes) of the drift accumulated since a reset of the
        estimate, given the distance travelled and the steps taken: what a robot can predict
        about its own error from its configuration (slip phases not included).

        uniform: steps * dim * e^2 / 3. distance: white noise sigma_w^2 d, scale error
        s^2 d^2, and the yaw random walk, whose integrated position effect is ~ sigma_y^2 d^3 / 3.
        """
        cfg = self.config
        if self._uniform:
            return steps * dim * cfg.uniform_error_m**2 / 3.0
        d = np.asarray(distance_m, dtype=float)
        # 2 sigma_w^2 d + s^2 d^2 + sigma_y^2 d^3 / 3, in Horner form (fewer array operations)
        c1, c2 = 2 * cfg.noise_std_m_per_sqrt_m**2, cfg.scale_error_std**2
        c3 = cfg.yaw_noise_std_rad_per_sqrt_m**2 / 3.0
        return d * (c1 + d * (c2 + c3 * d))

