"""The localization system the environments wrap: simulator + calibration rounds + solver.

Free of RL APIs (the PettingZoo and Gymnasium envs are thin adapters over this class).

Anchors know their positions only through the embedded solver (at calibrations) and their
odometry (between calibrations); tags are fixed every step from their ranges to the
*estimated* anchor positions. Ground truth is used only for the error metrics.

Frame: the first calibration (run during :meth:`reset`, paper rules) defines the localization
frame; the simulator's estimate frame is set to the rigid transform that best maps the true
anchor positions onto that solution, so errors are measured where users see positions.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from uwb_env.config import ConfigError, EnvConfig
from uwb_env.features import anchor_features
from uwb_env.localization import GeometryError, LocalizationError, calibrate_anchors, locate_tags, rigid_align
from uwb_env.localization._tracking_kernel import residual_statistics
from uwb_env.localization.calibration import calibrate_anchors_known_heights, horizontal_ranges
from uwb_env.localization.multilateration import (
    TAG_NO_FIX,
    TAG_OK,
    TAG_POOR_FIT,
    check_mirror_3d,
    fix_tags_2d,
    tag_fit_rejected,
)
from uwb_env.localization.relocation import relocate_anchor
from uwb_env.measurements import pool_rounds
from uwb_env.rewards import reward_terms
from uwb_env.sim import RangeModel, World
from uwb_env.sim.calibration_round import busy_fraction
from uwb_env.sim.planar_errors import planar_errors
from uwb_env.sim.round_path import RoundPath, pair_mean_times_s
from uwb_env.team_state import CALIBRATION_FIT_NAMES, FIT_ERROR, RoundSolutions, TeamState, solve_later_rounds


def _first_rank(result) -> tuple:
    """Order of preference among first-calibration results that are not clean."""
    return (CALIBRATION_FIT_NAMES.index(result.status), result.ambiguous, result.chi2 / max(result.dof, 1))

OBS_FIELDS = (
    "time_since_calibration_s",
    "predicted_position_std_m",
    "calibration_position_std_m",
    "last_calibration_rms_residual_m",
    "tag_fix_rms_residual_m",
    "own_range_residual_m",
    "calibrating",
    "round_progress",
)


@dataclass
class StepReport:
    """What happened in one step (ground-truth metrics included)."""

    round_started: bool
    round_finished: bool
    requests_ignored: int
    calibrating_fraction: float
    calibration_failed: str | None = None
    # -1 for a team round (or none); the re-locating anchor's index for a per-anchor round
    round_anchor: int = -1


# ndarray.sum goes through a Python wrapper; on the few-element arrays of one env step the
# ufunc's own reduce is measurably cheaper (axis defaults to 0; None for all axes).
_sum = np.add.reduce


class LocalizationSystem:
    """Anchors, tags, calibration rounds and the embedded solver, stepped together.

    Args:
        config: the environment configuration (its ``sim`` part configures the world).
    """

    def __init__(self, config: EnvConfig | None = None, range_model: RangeModel | None = None, world=None):
        self.config = config or EnvConfig()
        # ``world``: anything with the World interface, e.g. the hardware backend (no truth).
        self.world = world if world is not None else World(self.config.sim, range_model)
        self.ground_truth = getattr(self.world, "has_ground_truth", True)
        if self.config.sim.known_heights_std_m is not None and not self.ground_truth:
            raise ConfigError("sim.known_heights_std_m", self.config.sim.known_heights_std_m,
                              "is simulated (drawn from the true heights): not available with this world")
        self.range_model = self.world.range_model
        self.n_anchors = self.config.sim.n_anchors
        self.n_tags = self.config.sim.n_tags
        self.dim = self.config.sim.dim
        # one corrected range's Gaussian noise (tag fixes, covariance floors) and, for the
        # K-averaged pair means of calibration rounds, its std with the NLOS excess's second
        # moment (without it a calibration's covariance is ~3x overconfident in NEES under
        # the default radio: benchmarks/bench_consistency.py)
        self.range_std_m = self.range_model.corrected_noise_std_m
        self.pair_range_std_m = self.range_model.corrected_range_std_m
        self.obs_size = self.dim + len(OBS_FIELDS)
        self._eye = np.eye(self.dim)
        self._bounds = self.feature_bounds()

    # -- lifecycle -----------------------------------------------------------------------------
    def reset(self, rng: np.random.Generator) -> None:
        """New episode: place robots, run the first calibration (paper rules), fix tags."""
        cfg = self.config
        n, m, dim = self.n_anchors, self.n_tags, self.dim
        self.world.reset(rng)
        # Per-step caches are keyed by step and calibration counts, which repeat across episodes.
        self._cache_stamp = self._transform_key = None
        # the calibration bookkeeping and tag tracks: a batch of one of the batched env's state
        # (uwb_env.team_state; the properties below are views of its row)
        self.state = TeamState.new(1, n, m, dim, cfg.residual_window_steps)
        self.anchor_round_count = 0
        self._estimates_epoch = 0  # calibrations applied (team and per-anchor): keys the per-step caches
        self.time_calibrating_s = 0.0
        self.tag_refits = 0  # cold re-solves of stuck tags (diagnostics)
        # the last team round's fit verdict (CALIBRATION_FIT_NAMES), shape ambiguity and chi2/dof
        self.calibration_fit, self.calibration_ambiguous, self.calibration_chi2_per_dof = 0, False, 0.0
        self.tag_mirror_switches = 0  # fixes the ranges rejected in favour of their mirror
        self._links_round = None  # the round whose links last_round_links shows (rendering)
        self._round_path = self._new_round_path()  # the first calibration's rounds, all of them
        self._known_z = None  # the anchors' known heights in the estimate frame (known_heights_std_m)
        result = self._first_calibration()
        # The solution describes the robots at the rounds' midpoint; the solver's frame
        # becomes the estimate frame: est = R (world - origin).
        path = self._round_path
        if self.ground_truth and self._heights_known:
            # heights known: the frame keeps the vertical (a turn about it, and a shift)
            truth = path.midpoint_truth()
            rot2, trans2 = rigid_align(truth[:, :2], result.positions[:, :2])
            rot, trans = np.eye(3), np.append(trans2, np.mean(result.positions[:, 2] - truth[:, 2]))
            rot[:2, :2] = rot2
            self._known_z = result.positions[:, 2].copy()
        elif self.ground_truth:
            rot, trans = rigid_align(path.midpoint_truth(), result.positions)
        else:  # on hardware the first calibration's frame simply is the frame
            rot, trans = np.eye(dim), np.zeros(dim)
        self.world.set_estimate_frame(rot, -rot.T @ trans)
        odometry_since_mid = (self.world.anchors_est - path.midpoint_estimates()) @ rot.T
        solutions = RoundSolutions(1, n, dim)
        solutions.put_result(0, result)
        # the frame was just set from this solution: it is applied whatever its verdict (a
        # not-converged 3D known-heights solve is still the frame's; the verdict is reported)
        self._apply_solutions(solutions, odometry_since_mid, path.midpoint_drift(), always=True)
        self._fix_tags()

    @property
    def _heights_known(self) -> bool:
        return self.dim == 3 and self.config.sim.known_heights_std_m is not None

    # views of the state's row (properties, not attributes bound at reset: a deepcopy or pickle
    # would copy bound views as arrays of their own, cut off from the state)
    time_since_calibration_s = property(lambda self: self.state.time_since_calibration_s[0])
    steps_since_calibration = property(lambda self: self.state.steps_since_calibration[0])
    calibration_var_m2 = property(lambda self: self.state.calibration_var_m2[0])
    anchor_cov = property(lambda self: self.state.anchor_cov[0])
    tag_fix = property(lambda self: self.state.tag_fix[0])
    tag_velocity = property(lambda self: self.state.tag_velocity[0])
    tag_fix_age_s = property(lambda self: self.state.tag_fix_age_s[0])
    tag_status = property(lambda self: self.state.tag_status[0], doc="multilateration.TAG_STATUS_NAMES per tag")

    @property
    def calibration_count(self) -> int:
        """Team calibrations applied this episode (the first one included)."""
        return int(self.state.calibration_count[0])

    @property
    def calibrations_poor_fit(self) -> int:
        return int(self.state.calibrations_poor_fit[0])

    @property
    def last_calibration_rms_m(self) -> float:
        return float(self.state.last_calibration_rms_m[0])

    def _new_round_path(self) -> RoundPath:
        world = self.world
        return RoundPath(world.time_s, world.anchors_est, world.odometry.snapshot(),
                         world.anchors_true if self.ground_truth else None)

    def _record_round_step(self) -> None:
        world = self.world
        self._round_path.record(world.time_s, world.anchors_est, world.odometry.snapshot(),
                                world.anchors_true if self.ground_truth else None)

    # Rounds the first calibration may take: each extra round adds its exchanges to the pool.
    FIRST_CALIBRATION_MAX_ROUNDS = 6

    def _first_calibration(self):
        """The paper's first calibration, run before the episode starts.

        A single round can fail to fix the frame (dropouts disconnect the range graph, or in 3D
        anchors on robots of similar height leave noisy ranges without a 3D embedding). A team
        would simply keep ranging: each further round is pooled with the earlier ones (more
        exchanges per pair, less noise) until the shape is determined.
        """
        cfg, best, last = self.config, None, None
        rounds = []  # (corrected matrix, its pair times) of every round so far
        for _ in range(self.FIRST_CALIBRATION_MAX_ROUNDS):
            world = self.world
            world.start_calibration_round()
            while not world.round.done:
                world.step()
                self._record_round_step()
            finished = world.finish_calibration_round()
            try:
                rounds.append((world.round_correction.correct_matrix(finished.result()), self._pair_times(finished)))
            except LocalizationError as err:
                last = err
                continue
            # every round carried to the midpoint of all of them (the solution's moment)
            pooled = None
            for matrix, times in rounds:
                carried = self._carried(matrix, times)
                pooled = carried if pooled is None else pool_rounds(pooled, carried)
            try:
                if self._heights_known:  # the plane from the ranges' horizontal parts, the heights given
                    result = calibrate_anchors_known_heights(
                        pooled, self.world.known_heights_m, cfg.sim.known_heights_std_m, mark_ambiguous=False,
                        loss=cfg.solver.loss, f_scale=cfg.solver.f_scale_sigmas, range_std_m=self.pair_range_std_m)
                else:
                    result = calibrate_anchors(
                        pooled, dim=self.dim, loss=cfg.solver.loss,
                        f_scale=cfg.solver.f_scale_sigmas, range_std_m=self.pair_range_std_m,
                    )
            except LocalizationError as err:
                last = err
                continue
            if result.status == "degenerate":
                # the best fit, but part of the shape is fixed only to second order (collinear
                # within the noise): no frame to fix on it; keep ranging, pooled
                last = GeometryError(result.message)
                continue
            # Without a prior, an ambiguous shape may be folded or mirrored in part: keep ranging
            # rather than fix the frame on it. A poor fit is kept (and reported): more rounds
            # pooled while the robots move would not make the ranges more consistent.
            if result.status != "not_converged" and not result.ambiguous:
                return result
            if best is None or _first_rank(result) <= _first_rank(best):
                best = result
        if best is not None and best.status != "not_converged":
            return best  # the verdict is reported (calibration_fit / calibration_ambiguous in infos)
        if pooled is not None and isinstance(last, GeometryError) and self.dim == 3:
            # The pooled ranges fit a flat shape within their noise, round after round (four
            # anchors at similar heights: the data cannot fix the heights). The robots know
            # their heights (the odometry integrates the vertical without error): the plane
            # from the ranges, the heights from the on-board estimates, reported ambiguous.
            est = self._round_path.midpoint_estimates()
            try:
                result = calibrate_anchors_known_heights(
                    pooled, est[:, 2], np.sqrt(np.maximum(self.predicted_anchor_var_m2(), self.range_std_m**2)),
                    loss=cfg.solver.loss, f_scale=cfg.solver.f_scale_sigmas, range_std_m=self.pair_range_std_m)
                if result.status != "degenerate":
                    return result
                last = GeometryError(result.message)
            except LocalizationError as err:
                last = err
        raise (type(last) if last else LocalizationError)(
            f"first calibration failed after {self.FIRST_CALIBRATION_MAX_ROUNDS} pooled rounds: "
            f"{last if last else best.message}")

    def step(self, requests: np.ndarray, move_commands: np.ndarray | None = None,
             anchor_requests: np.ndarray | None = None) -> StepReport:
        """Advance one ``dt_s``.

        Args:
            requests: (n_anchors,) bool, each anchor's request for a team round.
            move_commands: optional (n_anchors, 2) [heading_rad, speed_mps] overrides.
            anchor_requests: optional (n_anchors,) bool, "re-locate me" (a per-anchor round). A
                triggered team round wins; otherwise the requester with the largest predicted
                error gets the channel (one round at a time).
        """
        world, dt = self.world, self.world.dt_s
        if move_commands is not None:
            self.world.motion.command(np.arange(self.n_anchors), move_commands[:, 0], move_commands[:, 1])
        running = world.round is not None
        asked = int(np.count_nonzero(requests)) + (int(np.count_nonzero(anchor_requests))
                                                   if anchor_requests is not None else 0)
        ignored = asked if running else 0
        started = (not running) and self._triggered(requests)
        round_anchor = -1
        if started:
            world.start_calibration_round()
            self._round_path = self._new_round_path()
        elif not running and anchor_requests is not None and anchor_requests.any():
            var = np.where(anchor_requests, self.predicted_anchor_var_m2(), -np.inf)
            round_anchor = int(np.argmax(var))
            world.start_calibration_round(initiators=[round_anchor])
            self._round_path = self._new_round_path()
            started = True
        t0 = world.time_s
        world.step()
        self.state.tick(dt)
        report = StepReport(started, False, ignored, 0.0, round_anchor=round_anchor)
        if world.round is not None:
            rnd = world.round
            self._record_round_step()
            report.calibrating_fraction = busy_fraction(rnd, t0, world.time_s, dt)
            self.time_calibrating_s += report.calibrating_fraction * dt
            self._links_round = rnd
            if rnd.done:
                report.round_finished = True
                report.calibration_failed = self._finish_round()
            self._hold_tags(dt)
        else:
            self._links_round = None
            self._fix_tags()
        return report

    @property
    def last_round_links(self) -> np.ndarray | None:
        """(E, 2) initiator / responder of the exchanges of the round running at the last step
        (None between rounds): what the renderer draws."""
        rnd = self._links_round
        return None if rnd is None else np.column_stack([rnd.initiator, rnd.responder])

    # -- calibration -----------------------------------------------------------------------------
    def _triggered(self, requests: np.ndarray) -> bool:
        k = int(np.count_nonzero(requests))
        rule = self.config.trigger
        if rule == "any":
            return k >= 1
        if rule == "majority":
            return k > self.n_anchors / 2
        return k == self.n_anchors

    def _finish_round(self) -> str | None:
        finished = self.world.finish_calibration_round()
        if getattr(finished, "initiators", None) is not None:
            return self._finish_anchor_round(finished)
        # Motion compensation: the ranges were taken while the robots moved, so the solution
        # describes them at the round's midpoint (each pair carried there along the estimated
        # path). Solve against the mid-round estimates and carry the result to now with the
        # odometry accumulated since then.
        path = self._round_path
        est_mid = path.midpoint_estimates()
        try:
            matrix = self.world.round_correction.correct_matrix(finished.result())  # hardware: raises on failure
            matrix = self._to_round_midpoint(matrix, finished)
        except LocalizationError as err:
            return f"{type(err).__name__}: {err}"
        # the batched env's solve for a team of one (compiled for the usual 2D round, the full
        # solver's starts and checks for whatever it hands back)
        prior_std = np.sqrt(np.maximum(self.predicted_anchor_var_m2(), self.range_std_m**2))
        carry = None if matrix.carry_var_m2 is None else matrix.carry_var_m2[None]
        if self._known_z is not None:  # the plane from the ranges' horizontal parts, the heights known
            z = self._known_z
            flat = horizontal_ranges(matrix.mean_m, z)
            planar = solve_later_rounds(flat[None], matrix.std_m[None], matrix.count[None], carry,
                                        est_mid[None, :, :2], prior_std[None], self.config.solver,
                                        self.pair_range_std_m)
            solutions = planar.with_heights(z[None], self.config.sim.known_heights_std_m)
        else:
            solutions = solve_later_rounds(matrix.mean_m[None], matrix.std_m[None], matrix.count[None], carry,
                                           est_mid[None], prior_std[None], self.config.solver, self.pair_range_std_m)
        return self._apply_solutions(solutions, self.world.anchors_est - est_mid, path.midpoint_drift())

    def _apply_solutions(self, solutions: RoundSolutions, since_mid: np.ndarray, drift_at_mid: dict,
                         always: bool = False) -> str | None:
        """Record the round's verdict and apply its solution (``TeamState.apply_calibrations``);
        the failure's message where there is none to apply (odometry kept). ``always``: apply a
        not-converged solution too (the first calibration, which has set the frame)."""
        fit = int(solutions.fit[0])
        if fit == FIT_ERROR:  # e.g. dropouts disconnected the graph
            return solutions.message[0]
        self.calibration_fit = fit
        self.calibration_ambiguous = bool(solutions.ambiguous[0])
        self.calibration_chi2_per_dof = float(solutions.chi2_per_dof[0])
        if not (always or solutions.applicable[0]):  # no solution to speak of: keep odometry, say why
            return solutions.message[0]
        self.state.apply_calibrations(slice(None), self.world.anchors_est[None], solutions, slice(None),
                                      since_mid[None])
        self._estimates_epoch += 1
        self.world.odometry.restart_drift(since=drift_at_mid)
        path = self._round_path
        self.world.calibration_applied(solutions.positions[0], np.trace(solutions.anchor_cov[0], axis1=1, axis2=2),
                                       path.times_s[0], path.times_s[-1])
        return None

    def _pair_times(self, finished) -> np.ndarray | None:
        times = getattr(finished, "times_s", None)  # None: PANS role-switching rounds (no known schedule)
        if times is None:
            return None
        return pair_mean_times_s(self.n_anchors, times, finished.initiator, finished.responder)

    def _to_round_midpoint(self, matrix, finished):
        return self._carried(matrix, self._pair_times(finished))

    def _carried(self, matrix, pair_times_s):
        """``matrix`` carried to the round path's midpoint, with the variance that adds."""
        path = self._round_path
        return replace(matrix, mean_m=path.carry(matrix.mean_m, pair_times_s),
                       carry_var_m2=path.carry_var_m2(pair_times_s, self.world.odometry))

    def _finish_anchor_round(self, finished) -> str | None:
        """One anchor re-located against the others (their estimates and covariances as known up
        to that covariance, its own odometry as the prior); the others keep their estimates."""
        (i,) = finished.initiators
        others = np.flatnonzero(np.arange(self.n_anchors) != i)
        path = self._round_path
        est_mid = path.midpoint_estimates()
        cov = self._predicted_covariance()
        try:
            matrix = self._to_round_midpoint(self.world.round_correction.correct_matrix(finished.result()), finished)
            count = matrix.count[i, others]
            ranges = np.where(count > 0, matrix.mean_m[i, others], np.nan)
            var = self.pair_range_std_m**2 / np.maximum(count, 1)
            if matrix.carry_var_m2 is not None:
                var = var + matrix.carry_var_m2[i, others]
            prior, prior_cov = est_mid[i], cov[i]
            if self._known_z is not None:  # the height is known: a sharp prior on it, uncoupled
                prior, prior_cov = prior.copy(), prior_cov.copy()
                prior[2] = self._known_z[i]
                prior_cov[2, :] = prior_cov[:, 2] = 0.0
                prior_cov[2, 2] = self.config.sim.known_heights_std_m**2
            res = relocate_anchor(ranges, est_mid[others], var,
                                  others_covariance=cov[others], prior=prior, prior_covariance=prior_cov)
        except LocalizationError as err:
            return f"{type(err).__name__}: {err}"
        if not res.ok:  # a mirror fix or a fit the noise cannot explain: keep odometry, say why
            return f"anchor {i} relocation {res.status} (chi2 {res.chi2:.1f} on {res.dof} dof)"
        self.world.anchors_est[i] = res.position + (self.world.anchors_est[i] - est_mid[i])
        self.anchor_cov[i] = res.covariance
        self.calibration_var_m2[i] = float(np.trace(res.covariance))
        self.anchor_round_count += 1
        self._estimates_epoch += 1
        self.time_since_calibration_s[i] = 0.0
        self.steps_since_calibration[i] = 0
        self.world.odometry.restart_drift(i, since={k: v[i] for k, v in path.midpoint_drift().items()})
        self.world.anchor_calibration_applied(i, path.times_s[0], path.times_s[-1])
        return None

    def _predicted_covariance(self) -> np.ndarray:
        """(n, dim, dim): the last calibration's covariance plus the drift model's (isotropic),
        floored at one range std so that a fresh anchor is never taken as exact."""
        pred = self.predicted_anchor_var_m2()
        drift = np.maximum(pred - self.calibration_var_m2, 0.0) / self.dim + self.range_std_m**2
        return self.anchor_cov + drift[:, None, None] * self._eye

    # -- tags ------------------------------------------------------------------------------------
    def predicted_anchor_var_m2(self) -> np.ndarray:
        """Each anchor's predicted position error variance: calibration + drift model."""
        odometry = self.world.odometry
        return self._cached("predicted_var", lambda: self.calibration_var_m2 + odometry.expected_drift_var_m2(self.dim))

    def _fix_tags(self) -> None:
        if self.n_tags == 0:
            return
        world = self.world
        raw = world.measure_tag_ranges().T  # (tags, anchors)
        # Noise can push a corrected range below zero next to an anchor: a valid reading of ~0.
        ranges = np.maximum(world.tag_correction.correct(raw), 0.0)
        solver = self.config.solver
        pred_var = self.predicted_anchor_var_m2()
        anchors = world.anchors_est
        st = self.state
        if self.dim == 2:
            # the batched env's tag fixing for a batch of one (one compiled pass: track, restart
            # stuck tags from the closed form, mirror check, residual statistics)
            step = fix_tags_2d(anchors[None], st.tag_fix, ranges[None], self.range_std_m**2, pred_var[None],
                               st.calibration_var_m2, st.anchor_cov if solver.use_anchor_covariance else None,
                               solver.loss, solver.tag_f_scale_sigmas, solver.tag_iterations,
                               solver.tag_restart_residual_m)
            positions, rms = step.positions, step.rms_m
            self.tag_refits += int(step.refit.sum())
            self.tag_mirror_switches += int(step.switched.sum())
            self.tag_status[:] = step.status[0]
            residuals = step.tag_residual_m, step.anchor_residual_m, step.any_fix
        else:
            positions, rms, residuals = self._fix_tags_3d(anchors, ranges, pred_var, solver)
            positions, rms = positions[None], rms[None]
        # the fixes, and the residual statistics: what a deployed system can see that its
        # anchors went stale (the batched env's bookkeeping, for a batch of one)
        st.record_tag_fixes(slice(None), positions, rms, *residuals, world.dt_s)

    def _fix_tags_3d(self, anchors, ranges, pred_var, solver) -> tuple:
        """3D tags: the general solver from the last fixes (restarting stuck ones), then the
        mirror check across the anchors' plane. Returns positions (M, 3), rms (M,) (NaN = no
        fix) and the residual statistics (``residual_statistics``, a batch of one); sets the
        tags' status."""
        cov = None
        if solver.use_anchor_covariance:  # calibration covariance + the isotropic drift part
            cov = self.anchor_cov + ((pred_var - self.calibration_var_m2) / self.dim)[:, None, None] * self._eye
        # Stale anchors raise every residual; only a residual well beyond what their predicted
        # error explains suggests a fix stuck in a wrong minimum (worth a cold restart).
        restart_m = solver.tag_restart_residual_m + 2.0 * math.sqrt(float(pred_var.max()))
        fix = locate_tags(
            anchors, ranges, self.range_std_m, anchor_covariance=cov, loss=solver.loss,
            f_scale=solver.tag_f_scale_sigmas, initial=self.tag_fix, max_iterations=solver.tag_iterations,
            with_covariance=False, restart_residual_m=restart_m,
        )
        positions, rms = fix.positions, np.where(fix.ok, fix.residual_rms_m, np.nan)
        var = self.range_std_m**2 + float(pred_var.mean()) / 2
        checked, status, switched = check_mirror_3d(anchors, positions, ranges, var, cov, solver.loss,
                                                    solver.tag_f_scale_sigmas)
        if switched.any():
            positions = checked
            self.tag_mirror_switches += int(switched.sum())
            res = np.linalg.norm(positions[:, None, :] - anchors[None], axis=-1) - ranges
            n_ranges = np.isfinite(res).sum(axis=1)  # a tag without ranges keeps its NaN
            mean_sq = np.nansum(res * res, axis=1) / np.maximum(n_ranges, 1)
            rms = np.where(np.isfinite(rms) & (n_ranges > 0), np.sqrt(mean_sq), rms)
        # the 2D step's fit test: a fix whose ranges the anchors cannot explain is a poor fit
        poor = (status == TAG_OK) & tag_fit_rejected(anchors, positions, ranges, self.range_std_m**2, pred_var)
        self.tag_status[:] = np.where(np.isfinite(rms), np.where(poor, TAG_POOR_FIT, status), TAG_NO_FIX)
        fixed = np.where(np.isfinite(rms)[:, None], positions, np.nan)
        return positions, rms, residual_statistics(anchors[None], fixed[None], ranges[None])

    def _hold_tags(self, dt: float) -> None:
        self.state.hold_tags(slice(None), dt, self.config.tag_fallback == "predict")

    # -- features and metrics ----------------------------------------------------------------------
    def anchor_features(self) -> np.ndarray:
        """(n_anchors, dim + len(OBS_FIELDS)) float32 features, clipped to the declared bounds
        (the batched env's kernel, ``features.anchor_features``, for a batch of one)."""
        world, st = self.world, self.state
        rnd = world.round
        low, high = self._bounds
        return anchor_features(
            world.anchors_est[None], st.time_since_calibration_s, self.predicted_anchor_var_m2()[None],
            st.calibration_var_m2, st.last_calibration_rms_m, st.tag_residual_hist, st.anchor_residual_hist,
            st.filled(),
            np.array([float(rnd is not None)]), np.array([rnd.progress if rnd is not None else 0.0]), low, high)[0]

    def feature_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        size, cap = self.config.sim.area_size_m, self.config.error_cap_m
        t_max = self.config.max_cycles * self.config.sim.dt_s + 60.0
        pos_lo = [-size - cap] * self.dim
        pos_hi = [2 * size + cap] * self.dim
        low = np.array(pos_lo + [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0], dtype=np.float32)
        high = np.array(pos_hi + [t_max, cap, cap, cap, cap, cap, 1.0, 1.0], dtype=np.float32)
        return low, high

    def _constellation_transform(self) -> tuple[np.ndarray, np.ndarray]:
        # Range-only calibration restores the constellation's shape, not where the frame has
        # drifted or turned (both unobservable from ranges). The paper measures positions
        # relative to the anchors, so errors are taken after the rigid transform (rotation +
        # translation) that best maps the true anchors onto their estimates; rotation_error_rad
        # and the "fixed" frame report the frame drift separately. Cached per step. (2D takes
        # the closed form in ``_planar_errors``.)
        key = self.world.step_count
        if getattr(self, "_transform_key", None) != key:
            truth = self.world.to_estimate_frame(self.world.anchors_true)
            self._transform = rigid_align(truth, self.world.anchors_est, allow_reflection=False)
            self._transform_key = key
        return self._transform

    def _truth(self, points_world: np.ndarray, frame: str) -> np.ndarray:
        truth = self.world.to_estimate_frame(points_world)
        if frame == "constellation":
            rot, trans = self._constellation_transform()
            return truth @ rot.T + trans
        if frame != "fixed":
            raise ValueError(f"frame={frame!r}: must be 'constellation' or 'fixed'")
        return truth

    def _planar_errors(self) -> dict:
        """Every truth metric of this step at once, for 2D (the envs' hot path): the compiled
        kernel the batched env uses too (``sim.planar_errors``), for a batch of one."""
        n, world = self.n_anchors, self.world
        truth = world.motion.positions
        a_const, t_const, a_fixed, t_fixed, rotation = planar_errors(
            world.frame_rotation[None], world.frame_origin[None], truth[None, :n], truth[None, n:],
            world.anchors_est[None], self.tag_fix[None], float(self.config.error_cap_m))
        return {("anchor", "constellation"): a_const[0], ("anchor", "fixed"): a_fixed[0],
                ("tag", "constellation"): t_const[0], ("tag", "fixed"): t_fixed[0], "rotation": float(rotation[0])}

    def anchor_errors_m(self, frame: str = "constellation") -> np.ndarray:
        """Per-anchor error; ``constellation`` (after rigid alignment) or ``fixed`` (first-calibration frame).
        NaN without ground truth (hardware)."""
        if not self.ground_truth:
            return np.full(self.n_anchors, np.nan)
        if self.dim == 2 and frame in ("constellation", "fixed"):
            return self._cached("planar", self._planar_errors)["anchor", frame]
        return self._cached(("anchor", frame), lambda: np.linalg.norm(
            self.world.anchors_est - self._truth(self.world.anchors_true, frame), axis=1))

    def tag_errors_m(self, frame: str = "constellation") -> np.ndarray:
        """Per-tag error of the current fix (held fixes keep aging); capped at ``error_cap_m``."""
        if not self.ground_truth:
            return np.full(self.n_tags, np.nan)
        if self.dim == 2 and frame in ("constellation", "fixed"):
            return self._cached("planar", self._planar_errors)["tag", frame]

        def compute():
            err = np.linalg.norm(self.tag_fix - self._truth(self.world.tags_true, frame), axis=1)
            return np.minimum(np.where(np.isfinite(err), err, self.config.error_cap_m), self.config.error_cap_m)

        return self._cached(("tag", frame), compute)

    def _cached(self, key, compute):
        # Metrics are read several times per step (reward, infos): compute each once per step.
        stamp = (self.world.step_count, self._estimates_epoch)
        if getattr(self, "_cache_stamp", None) != stamp:
            self._cache_stamp, self._cache = stamp, {}
        if key not in self._cache:
            self._cache[key] = compute()
        return self._cache[key]

    def rotation_error_rad(self) -> float:
        """Paper Fig. 5: angle between the estimated and true direction anchor 0 -> anchor 1
        (in the fixed frame of the first calibration)."""
        if not self.ground_truth:
            return float("nan")
        if self.dim == 2:
            return self._cached("planar", self._planar_errors)["rotation"]
        truth = self.world.to_estimate_frame(self.world.anchors_true[:2])
        est = self.world.anchors_est[:2]
        a, b = est[1] - est[0], truth[1] - truth[0]
        return float(abs(np.arctan2(a[0] * b[1] - a[1] * b[0], a @ b)))

    def reward_terms(self, report: StepReport) -> dict[str, float]:
        cfg = self.config
        if self.ground_truth:
            tag = float(_sum(self.tag_errors_m())) / self.n_tags if self.n_tags else 0.0
            anchor = float(_sum(np.fmin(self.anchor_errors_m(), cfg.error_cap_m))) / self.n_anchors
        else:
            # Residual proxy (no truth on hardware): the tag fixes' RMS residual since the last
            # calibration stands for the tag error, the predicted std for the anchor error.
            filled = int(self.state.filled()[0])
            tag = float(self.state.tag_residual_hist[0, :filled].mean()) if filled else 0.0
            anchor = float(np.sqrt(self.predicted_anchor_var_m2()).mean())
        return reward_terms(cfg, tag, anchor, report.calibrating_fraction, float(report.round_started))
