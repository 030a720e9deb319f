"""On-board odometry: how each anchor's position estimate drifts between calibrations.

Both models turn the true displacement of a step into the displacement the robot *believes*
it made; the world adds that to the on-board estimate.
"""

from __future__ import annotations

import numpy as np

from uwb_env.config import OdometryConfig
from uwb_env.sim._odometry_kernel import drift_step, drift_variance, drift_variance_between, recentre, slip_step
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
        # What each robot can predict of its own drift from what it measured and its
        # configuration (see expected_drift_var_m2): the heading error's variance (slips in
        # expectation; a position calibration does not observe heading, so it keeps growing
        # across calibrations) and, since the last restart_drift: the distance, the steps, the
        # net displacement P (complex, planar) and the sums A = sum dv_k, B = sum dv_k P_k,
        # C = sum dv_k |P_k|^2 over the heading-variance increments dv_k.
        self.heading_var_rad2 = np.zeros(n)
        self._h0 = np.zeros(n)
        self._dist = np.zeros(n)
        self._steps = np.zeros(n)
        self._net = np.zeros(n, dtype=complex)
        self._sum_a = np.zeros(n)
        self._sum_b = np.zeros(n, dtype=complex)
        self._sum_c = np.zeros(n)
        self._ones = np.ones(n)
        self._restarts = np.zeros(n, dtype=np.int64)  # a snapshot's drift is only comparable within one

    _ACCUMULATORS = ("heading_var_rad2", "_dist", "_steps", "_net", "_sum_a", "_sum_b", "_sum_c")

    def estimated_displacement(
        self, delta: np.ndarray, turn_rad: np.ndarray, dt_s: float, rng: np.random.Generator
    ) -> np.ndarray:
        """Displacement the robots believe they made, given the true ``delta`` (n, dim)."""
        cfg = self.config
        n, dim = delta.shape
        if self._uniform:
            # Paper: U(-e, e) added to every axis of the estimate every step.
            e = cfg.uniform_error_m
            self._steps += 1
            return delta + rng.uniform(-e, e, (n, dim))
        # 4n normals: [0, 2n) complex white noise, [2n, 3n) yaw increments, [3n, 4n) slip starts.
        noise = rng.standard_normal(4 * n)
        gain = None  # per-robot noise multiplier while slipping; None: nobody slips
        if cfg.slip_rate_per_s > 0.0:
            if dt_s != self._slip_dt_s:  # the threshold depends on dt only: compute it once
                self._slip_dt_s, self._slip_q = dt_s, upper_tail_threshold(cfg.slip_rate_per_s * dt_s)
            # Slips are rare: no per-robot bookkeeping while nobody slips or starts to.
            gain_buf = np.empty(n)
            touched, any_slip = slip_step(self.slip_left_s, noise, self._slip_q, self._any_slip, float(dt_s),
                                          cfg.slip_duration_s, cfg.slip_noise_multiplier, gain_buf)
            if touched:
                self._any_slip, gain = any_slip, gain_buf
        planar = np.empty((n, 2))
        drift_step(delta, turn_rad, noise, self.scale, self._ones if gain is None else gain, self.yaw_error_rad,
                   self._yaw_var_per_m, self._yaw_var_per_rad, cfg.noise_std_m_per_sqrt_m, self.expected_slip_gain2,
                   self.heading_var_rad2, self._net, self._sum_a, self._sum_b, self._sum_c, self._dist, self._steps,
                   planar)
        if dim == 2:
            return planar
        out = delta.copy()  # the vertical part is integrated without error
        out[:, :2] = planar
        return out

    def _accumulate(self, measured: np.ndarray, yaw_var: np.ndarray) -> None:
        """One step of what the robot measured: planar displacement (complex), the nominal
        variance of its heading increment (applied before this step's displacement)."""
        dv = self.expected_slip_gain2 * yaw_var
        self.heading_var_rad2 = self.heading_var_rad2 + dv
        p = self._net
        self._sum_a = self._sum_a + dv
        self._sum_b = self._sum_b + dv * p
        self._sum_c = self._sum_c + dv * (p.real * p.real + p.imag * p.imag)
        self._net = p + measured
        self._dist = self._dist + np.abs(measured)
        self._steps += 1

    def note_motion(self, displacement: np.ndarray) -> None:
        """Account for motion measured elsewhere (hardware odometry), (n, dim) per step."""
        if self._uniform:
            self._steps += 1
            return
        planar = np.ascontiguousarray(np.asarray(displacement, dtype=float)[:, :2]).view(np.complex128)[:, 0]
        self._accumulate(planar, self._yaw_var_per_m * np.abs(planar))

    def snapshot(self, robots=slice(None)) -> dict:
        """The drift accumulators of ``robots`` now (for :meth:`restart_drift`'s ``since``)."""
        out = {name: getattr(self, name)[robots].copy() for name in self._ACCUMULATORS}
        out["restarts"] = self._restarts[robots].copy()
        return out

    @property
    def planar(self) -> bool:
        """Whether the drift is in the horizontal plane only (``distance``: the vertical part is
        integrated without error) rather than on every axis (``uniform``)."""
        return not self._uniform

    def restart_drift(self, robots=slice(None), since: dict | None = None) -> None:
        """The estimates of ``robots`` (an index or mask) were just reset by a calibration.

        ``since``: a :meth:`snapshot` of the same robots. The calibration solved for the
        positions at that moment (a round's midpoint: ranges carried there) and the estimates
        are that solution plus the odometry since, so the drift since the snapshot stays
        predicted: the accumulators are re-centred on it (exactly: P -> P - P_s,
        B -> (B - B_s) - (A - A_s) P_s, C -> (C - C_s) - 2 Re(conj(P_s) (B - B_s)) + (A - A_s) |P_s|^2,
        the heading variance then carried). Without it the drift restarts from zero.
        """
        self._restarts[robots] += 1
        if since is None:
            self._h0[robots] = self.heading_var_rad2[robots]
            for name in self._ACCUMULATORS[1:]:  # all but the heading variance, which carries on
                getattr(self, name)[robots] = 0.0
            return
        for name, value in _recentred(since, self.snapshot(robots)).items():
            getattr(self, name)[robots] = value

    def expected_drift_var_m2(self, dim: int = 2, robots=slice(None)) -> np.ndarray:
        """(n,) (or of ``robots``, an index) expected variance (summed over axes) of each robot's drift since its last
        :meth:`restart_drift`, from what it measured and its configuration.

        uniform: steps * dim * e^2 / 3. distance, with P the net displacement since the
        restart and d the path length: white noise g 2 sigma_w^2 d (g: slips in expectation,
        :attr:`expected_slip_gain2`); scale error s^2 |P|^2; the heading error from before the
        restart, v0 |P|^2; and each heading increment since (variance dv_k, at P_k) turning the
        rest of the path, sum dv_k |P - P_k|^2 = A |P|^2 - 2 Re(P conj B) + C (a straight path
        of length d gives g sigma_y^2 d^3 / 3). Small-angle, first order.
        """
        cfg = self.config
        if self._uniform:
            return self._steps[robots] * dim * cfg.uniform_error_m**2 / 3.0
        arrays = [getattr(self, name) for name in ("_net", "_sum_b", "_dist", "_h0", "_sum_a", "_sum_c")]
        shape = self._h0.shape
        if not (isinstance(robots, slice) and robots == slice(None)):
            # any index numpy takes (int, mask, array of any shape): the compiled loop runs flat
            shape = np.shape(self._h0[robots])
            arrays = [np.ravel(a[robots]) for a in arrays]
        out = drift_variance(*arrays, *self._variance_constants())
        return out.reshape(shape)[()]  # a numpy scalar for an int index, as numpy's indexing gives

    def _variance_constants(self) -> tuple[float, float]:
        """The distance model's white-noise variance per metre and the scale error's variance."""
        cfg = self.config
        return 2 * cfg.noise_std_m_per_sqrt_m**2 * self.expected_slip_gain2, cfg.scale_error_std**2

    def drift_var_between(self, earlier: dict, later: dict, dim: int = 2) -> np.ndarray:
        """Expected variance (summed over axes) of the drift the robots of two :meth:`snapshot`
        accrued between them: :meth:`expected_drift_var_m2` as if the drift had restarted at
        ``earlier`` (the same re-centring as :meth:`restart_drift`), evaluated at ``later``.
        Both snapshots must lie after the robots' last restart (e.g. within one round)."""
        return self.drift_var_series([earlier, later], [0], [1], dim)[0]

    def drift_var_series(self, snapshots: list[dict], earlier, later, dim: int = 2) -> np.ndarray:
        """:meth:`drift_var_between` of ``snapshots[earlier[q]]`` and ``snapshots[later[q]]`` for
        every q at once (one compiled loop): (Q, *robots' shape)."""
        names = ("restarts", "_steps") if self._uniform else ("restarts", "heading_var_rad2", "_net", "_sum_a",
                                                              "_sum_b", "_sum_c", "_dist")
        stack = {name: np.array([s[name] for s in snapshots]) for name in names}
        earlier, later = np.asarray(earlier, dtype=np.int64), np.asarray(later, dtype=np.int64)
        if np.any(stack["restarts"][earlier] != stack["restarts"][later]):
            raise ValueError("drift_var_between: a restart_drift lies between the two snapshots")
        if self._uniform:
            return (stack["_steps"][later] - stack["_steps"][earlier]) * dim * self.config.uniform_error_m**2 / 3.0
        shape = stack["_net"].shape
        flat = {name: v.reshape(shape[0], -1) for name, v in stack.items()}
        out = drift_variance_between(flat["heading_var_rad2"], flat["_net"], flat["_sum_a"], flat["_sum_b"],
                                     flat["_sum_c"], flat["_dist"], earlier, later, *self._variance_constants())
        return out.reshape((len(earlier),) + shape[1:])

    @property
    def expected_slip_gain2(self) -> float:
        """E[gain^2] of the noise over time: slips start at ``slip_rate_per_s`` while not slipping
        and last ``slip_duration_s``, so a fraction f = rT / (1 + rT) of the time is spent slipping
        with the noise multiplied by m; the variance grows by 1 + f (m^2 - 1) on average. A robot
        cannot see its slips (they are what calibration is for), but it can expect them."""
        cfg = self.config
        rt = cfg.slip_rate_per_s * cfg.slip_duration_s
        return 1.0 + rt / (1.0 + rt) * (cfg.slip_noise_multiplier**2 - 1.0)


def _recentred(since: dict, now: dict) -> dict:
    """The drift accumulators of :meth:`OdometryModel.snapshot` ``now`` as if the drift had
    restarted at the snapshot ``since`` (the same robots): P -> P - P_s, B -> (B - B_s) -
    (A - A_s) P_s, C -> (C - C_s) - 2 Re(conj(P_s) (B - B_s)) + (A - A_s) |P_s|^2
    (``_odometry_kernel._recentre``), the heading variance at ``since`` as ``_h0``."""
    shape = np.shape(now["_net"])
    flat = [np.ascontiguousarray(np.reshape(d[name], -1)) for d in (since, now)
            for name in ("_net", "_sum_a", "_sum_b", "_sum_c", "_dist")]
    net, sum_a, sum_b, sum_c, dist = (v.reshape(shape) for v in recentre(*flat))
    return {"_h0": since["heading_var_rad2"], "_dist": dist, "_steps": now["_steps"] - since["_steps"],
            "_net": net, "_sum_a": sum_a, "_sum_b": sum_b, "_sum_c": sum_c}
