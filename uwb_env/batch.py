"""Many copies of the scheduling task stepped together in numpy (the batched mode).

:class:`BatchedSystem` runs B copies of :class:`~uwb_env.system.LocalizationSystem`'s dynamics
with one decision per copy (the centralized scheduler): one motion kernel moves the robots of
all copies, one odometry model drifts all anchors, one call of the single env's tag fixing
(``multilateration.fix_tags_2d``: tracking, restarts, mirror check, residual statistics) fixes
the tags of all copies (each tag against its own copy's anchors), and features, errors and
rewards are computed for all copies at once. The pieces are the single env's: World's
placement, the round's exchange simulation (copies that start a round on the same step form a
:class:`~uwb_env.sim.round_cohort.RoundCohort`), the same motion compensation, and the
calibrations of all copies in one batched solve (``batched_calibration``, tested equal to the
full solver); only what that solve hands back (missing pairs, thin layouts, pair rejection) goes
to the full solver per copy. That solve, the update a calibration makes and the tag tracks and
residual buffers are :mod:`uwb_env.team_state`'s, the very code the single env runs for a batch
of one.

Later rounds of 3-4 anchors that fit poorly take the full solver's further steps batched too
(``later_calibrations(poor_fit_prior_std_m=...)``: cold starts, pick, unfold; 0 of ~7,400 kept
answers differ from the full solver's in ``tests/test_round_cohort.py``'s draws and two more
generators); the ambiguous ones and those with a start that does not converge go back to it.

Differences from the single env, by design: 2D only, the centralized ``calibrate`` action only;
episodes of all copies start and end together (same ``max_cycles``); the first calibration is
one round (the single env pools more while the shape is ambiguous); one generator drives the
batch (same seed, same batch).
Episode statistics match the single env's in distribution (tested with a two-sample KS test).
"""

from __future__ import annotations

import numpy as np

from uwb_env.config import EnvConfig
from uwb_env.features import anchor_features
from uwb_env.localization import calibrate_anchors
from uwb_env.localization.alignment import rigid_align_batch
from uwb_env.localization.batched_calibration import STATUS_NONE, first_calibrations, symmetric_arrays
from uwb_env.localization.errors import LocalizationError
from uwb_env.localization.multilateration import fix_tags_2d
from uwb_env.measurements import RangeMatrix
from uwb_env.rewards import reward_terms
from uwb_env.sim._odometry_kernel import add_rotated
from uwb_env.sim.calibration_round import busy_fraction
from uwb_env.sim.motion import MotionModel
from uwb_env.sim.odometry import OdometryModel
from uwb_env.sim.planar_errors import planar_errors
from uwb_env.sim.ranging import planar_distances
from uwb_env.sim.round_cohort import RoundCohort
from uwb_env.sim.round_path import RoundPath
from uwb_env.sim.world import formation_xy, tags_inside
from uwb_env.system import OBS_FIELDS, LocalizationSystem
from uwb_env.team_state import RoundSolutions, TeamState, solve_later_rounds


class BatchedSystem:
    def __init__(self, config: EnvConfig | None, n_copies: int):
        self.config = config or EnvConfig()
        sim = self.config.sim
        if sim.dim != 2:
            raise ValueError(f"sim.dim={sim.dim!r}: the batched mode is 2D only")
        if n_copies < 1:
            raise ValueError(f"n_copies={n_copies!r}: must be >= 1")
        self.B, self.N, self.M = n_copies, sim.n_anchors, sim.n_tags
        self._template = LocalizationSystem(self.config)  # feature bounds, range model, timing
        self.range_model = self._template.range_model
        self.range_std_m = self._template.range_std_m
        self.pair_range_std_m = self._template.pair_range_std_m
        self.timing = self._template.world.timing
        self.dt_s = sim.dt_s
        self.motion = MotionModel([(sim.anchor_motion, self.B * self.N), (sim.tag_motion, self.B * self.M)],
                                  sim.area_size_m, copies=self.B)
        self.odometry = OdometryModel(sim.odometry)
        self.obs_low, self.obs_high = self._template.feature_bounds()
        self.obs_size = 2 + len(OBS_FIELDS)

    # -- views into the motion state ---------------------------------------------------------------
    @property
    def anchors_true(self) -> np.ndarray:
        return self.motion.positions[: self.B * self.N].reshape(self.B, self.N, 2)

    @property
    def tags_true(self) -> np.ndarray:
        return self.motion.positions[self.B * self.N:].reshape(self.B, self.M, 2)

    # -- lifecycle ---------------------------------------------------------------------------------
    def reset(self, rng: np.random.Generator) -> None:
        cfg, B, N, M = self.config, self.B, self.N, self.M
        self.rng = rng
        anchors, tags = self._initial_positions(rng)
        self.motion.reset(np.vstack([anchors.reshape(B * N, 2), tags.reshape(B * M, 2)]), rng)
        self.odometry.reset(B * N, rng)
        self.time_s, self.step_count = 0.0, 0
        self.anchors_est = self.anchors_true.copy()
        self.frame_rot = np.tile(np.eye(2), (B, 1, 1))
        self.frame_origin = np.zeros((B, 2))
        self._cohorts: dict[int, RoundCohort] = {}
        self._cohort_of = np.full(B, -1)
        self._next_cohort = 0
        self.time_calibrating_s = np.zeros(B)
        # calibration bookkeeping, tag tracks, residual buffers: the single env's, for B teams
        self.state = TeamState.new(B, N, M, 2, cfg.residual_window_steps)
        # First calibration of every copy (paper rules), robots moving meanwhile: one cohort.
        self._start_rounds(np.arange(B))
        (cohort,) = self._cohorts.values()
        while not cohort.done:
            self._advance_world()
        path = cohort.path
        true_mid, est_mid, drift_mid = path.midpoint_truth(), path.midpoint_estimates(), path.midpoint_drift()
        mean, std, count, carry = self._round_statistics(cohort)
        est_now = self.anchors_est
        complete, pairs, dist, var = symmetric_arrays(mean, count, self.pair_range_std_m, carry)
        solver = cfg.solver
        solutions = RoundSolutions(B, N, 2)
        rows = np.flatnonzero(complete)
        solved = first_calibrations(pairs, dist[rows], var[rows], solver.loss, solver.f_scale_sigmas)
        done = solved.status != STATUS_NONE
        solutions.put_solved(rows[done], solved.subset(done))
        for k in np.flatnonzero(~solutions.compiled):  # thin layouts, missing pairs, poor fits: the full solver
            try:
                matrix = RangeMatrix(mean[k], std[k], count[k], _row(carry, k))
                solutions.put_result(k, calibrate_anchors(matrix, dim=2, loss=solver.loss,
                                                          f_scale=solver.f_scale_sigmas,
                                                          range_std_m=self.pair_range_std_m))
            except LocalizationError as err:  # e.g. dropouts disconnected the graph: no shape this round
                solutions.put_error(k, err)
        # A copy without a usable first calibration keeps its starting estimates in the world
        # frame (calibration_count 0: its features say it was never calibrated).
        ok = solutions.applicable
        positions = np.where(ok[:, None, None], solutions.positions, est_now)
        rot, origin = rigid_align_batch(true_mid, positions)  # estimate = truth @ R.T + t, per copy
        rot[~ok], origin[~ok] = np.eye(2), 0.0
        self.frame_rot, self.frame_origin = rot, -np.einsum("bji,bj->bi", rot, origin)
        since_mid = np.einsum("bnj,bij->bni", est_now - est_mid, rot)
        ks = np.flatnonzero(ok)
        self._apply(ks, solutions, ks, since_mid[ks], _drift_rows(drift_mid, self.N, ks))
        self._end_cohort(cohort)
        self._fix_tags(np.ones(B, dtype=bool), cold=True)

    def _initial_positions(self, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """The single env's placement (``World``'s formation and tags), for every copy at once."""
        anchors = formation_xy(self.config.sim, rng, copies=self.B)
        return anchors, tags_inside(anchors, self.M, rng)

    def step(self, requests: np.ndarray) -> dict[str, np.ndarray]:
        """Advance every copy by ``dt_s``; ``requests`` (B,) bool start rounds where none runs."""
        B = self.B
        requests = np.asarray(requests, dtype=bool).reshape(B)
        started = requests & (self._cohort_of < 0)
        if started.any():
            self._start_rounds(np.flatnonzero(started))
        t0 = self.time_s
        self._advance_world()
        self.state.tick(self.dt_s)
        busy = np.zeros(B)
        finished = np.zeros(B, dtype=bool)
        failed = np.zeros(B, dtype=bool)
        in_round = self._cohort_of >= 0
        for cohort in list(self._cohorts.values()):
            busy[cohort.copies] = busy_fraction(cohort, t0, self.time_s, self.dt_s)
            if cohort.done:
                finished[cohort.copies] = True
                failed[cohort.copies] = ~self._finish_cohort(cohort)
        self.time_calibrating_s += busy * self.dt_s
        # tags hold during rounds (and on the step a round ends, like the single env)
        if in_round.any():
            self.state.hold_tags(in_round, self.dt_s, self.config.tag_fallback == "predict")
        self._fix_tags(~in_round)
        return {"round_started": started, "round_finished": finished & ~failed, "calibration_failed": failed,
                "calibrating_fraction": busy}

    # -- world ---------------------------------------------------------------------------------------
    def _advance_world(self) -> None:
        B, N = self.B, self.N
        running = [c for c in self._cohorts.values() if not c.done]
        before = self.anchors_true.copy() if running else None
        delta, turn = self.motion.step(self.dt_s, self.rng)
        odo = self.odometry.estimated_displacement(delta[: B * N], turn[: B * N], self.dt_s, self.rng)
        add_rotated(self.anchors_est, odo.reshape(B, N, 2), self.frame_rot)  # odometry in each copy's frame
        t0 = self.time_s
        self.step_count += 1
        self.time_s = self.step_count * self.dt_s
        after = self.anchors_true
        for cohort in running:
            cohort.advance(t0, self.time_s, before[cohort.copies], after[cohort.copies], self.range_model, self.rng)
            cohort.path.record(self.time_s, self.anchors_est[cohort.copies], self.odometry.snapshot(cohort.robots),
                               after[cohort.copies])

    # -- calibration rounds: copies that start on the same step share a schedule (a cohort) --------
    def _start_rounds(self, copies: np.ndarray) -> None:
        k_pairs = self.config.sim.calibration.measurements_per_pair
        cohort = RoundCohort(copies, self.N, self.timing, k_pairs, self.time_s)
        self._cohorts[self._next_cohort] = cohort
        self._cohort_of[copies] = self._next_cohort
        self._next_cohort += 1
        # the estimated path through the round: its midpoint is where the solution is placed
        cohort.robots = self._robots_of(copies)
        cohort.path = RoundPath(self.time_s, self.anchors_est[copies], self.odometry.snapshot(cohort.robots),
                                self.anchors_true[copies])

    def _end_cohort(self, cohort: RoundCohort) -> None:
        del self._cohorts[int(self._cohort_of[cohort.copies[0]])]
        self._cohort_of[cohort.copies] = -1

    def _round_statistics(self, cohort: RoundCohort):
        """Bias-corrected per-pair mean (carried to the round's midpoint), std, count and carry
        variance (or None) of a finished cohort, (C, N, N) each: the single env's round result,
        for all copies at once."""
        mean, std, count = cohort.pair_statistics()
        mean, std = self.range_model.correct(mean), self.range_model.correct_std(std)
        times = cohort.pair_mean_times_s()
        return cohort.path.carry(mean, times), std, count, cohort.path.carry_var_m2(times, self.odometry)

    def _finish_cohort(self, cohort: RoundCohort) -> np.ndarray:
        """Solve the rounds of a finished cohort (``team_state.solve_later_rounds``: the usual
        case in one batched Gauss-Newton, the rest with the full solver per copy) and apply
        them. Returns ok per copy."""
        copies = cohort.copies
        mean, std, count, carry = self._round_statistics(cohort)
        self._end_cohort(cohort)
        est_mid, drift_mid = cohort.path.midpoint_estimates(), cohort.path.midpoint_drift()
        prior_std = np.sqrt(np.maximum(self.predicted_anchor_var_m2()[copies], self.range_std_m**2))
        solutions = solve_later_rounds(mean, std, count, carry, est_mid, prior_std, self.config.solver,
                                       self.pair_range_std_m)
        ok = solutions.applicable
        rows = np.flatnonzero(ok)
        self._apply(copies[rows], solutions, rows, self.anchors_est[copies[rows]] - est_mid[rows],
                    _drift_rows(drift_mid, self.N, rows))
        return ok

    def _apply(self, ks: np.ndarray, solutions: RoundSolutions, which: np.ndarray, since_mid: np.ndarray,
               drift_mid: dict) -> None:
        """Copies ``ks`` take ``solutions``' teams ``which`` (the single env's update) and
        restart their robots' drift from the round's midpoint."""
        if not len(ks):
            return
        self.state.apply_calibrations(ks, self.anchors_est, solutions, which, since_mid)
        self.odometry.restart_drift(self._robots_of(ks), since=drift_mid)

    # -- views of the state (uwb_env.team_state.TeamState: (B, ...) arrays, as before it existed) -----
    calibration_count = property(lambda self: self.state.calibration_count)
    calibration_var_m2 = property(lambda self: self.state.calibration_var_m2)
    anchor_cov = property(lambda self: self.state.anchor_cov)
    last_calibration_rms_m = property(lambda self: self.state.last_calibration_rms_m)
    time_since_calibration_s = property(lambda self: self.state.time_since_calibration_s)
    steps_since_calibration = property(lambda self: self.state.steps_since_calibration)
    tag_fix = property(lambda self: self.state.tag_fix)
    tag_velocity = property(lambda self: self.state.tag_velocity)
    tag_status = property(lambda self: self.state.tag_status)

    # -- tags --------------------------------------------------------------------------------------
    def _robots_of(self, copies) -> np.ndarray:
        mask = np.zeros(self.B, dtype=bool)
        mask[copies] = True
        return np.repeat(mask, self.N)


    def predicted_anchor_var_m2(self) -> np.ndarray:
        return self.state.calibration_var_m2 + self.odometry.expected_drift_var_m2(2).reshape(self.B, self.N)

    def _fix_tags(self, copies: np.ndarray, cold: bool = False) -> None:
        if self.M == 0 or not copies.any():
            return
        sel = np.flatnonzero(copies)
        # every copy (no round running anywhere, the usual step): views instead of gathered copies
        rows = slice(None) if len(sel) == self.B else sel
        # ranges only where tags are being fixed (no ranging while a copy's round runs)
        d = planar_distances(self.tags_true[rows], self.anchors_true[rows])
        raw = self.range_model.measure(d, self.rng)  # (S, M, N)
        ranges = np.maximum(self.range_model.correct(raw), 0.0)
        anchors = self.anchors_est[rows]
        solver = self.config.solver
        st = self.state
        # the single env's tag fixing (one compiled pass: track, restart, mirror check,
        # residual statistics); at reset (cold) every tag starts from the closed form
        previous = np.full((len(sel), self.M, 2), np.nan) if cold else st.tag_fix[rows]
        step = fix_tags_2d(anchors, previous, ranges, self.range_std_m**2, self.predicted_anchor_var_m2()[rows],
                           st.calibration_var_m2[rows], st.anchor_cov[rows] if solver.use_anchor_covariance
                           else None, solver.loss, solver.tag_f_scale_sigmas, solver.tag_iterations,
                           solver.tag_restart_residual_m)
        st.tag_status[rows] = step.status
        st.record_tag_fixes(rows, step.positions, step.rms_m, step.tag_residual_m, step.anchor_residual_m,
                            step.any_fix, self.dt_s)

    # -- observations and metrics --------------------------------------------------------------------
    def features(self) -> np.ndarray:
        """(B, N, 2 + 8) float32 features, the single env's fields and kernel
        (``features.anchor_features``), clipped into its bounds."""
        progress = np.zeros(self.B)
        for cohort in self._cohorts.values():
            progress[cohort.copies] = cohort.progress
        st = self.state
        return anchor_features(self.anchors_est, st.time_since_calibration_s, self.predicted_anchor_var_m2(),
                               st.calibration_var_m2, st.last_calibration_rms_m, st.tag_residual_hist,
                               st.anchor_residual_hist, st.filled(), (self._cohort_of >= 0).astype(np.float64),
                               progress, self.obs_low, self.obs_high)

    def errors_m(self) -> tuple[np.ndarray, np.ndarray]:
        """(B, N) anchor and (B, M) tag errors after each copy's rigid constellation alignment
        (the single env's kernel, ``sim.planar_errors``), tag errors capped at ``error_cap_m``."""
        a_const, t_const, _, _, _ = planar_errors(self.frame_rot, self.frame_origin, self.anchors_true, self.tags_true,
                                                  self.anchors_est, self.state.tag_fix, float(self.config.error_cap_m),
                                                  False)
        return a_const, t_const

    def rewards(self, report: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        cfg = self.config
        anchor_err, tag_err = self.errors_m()
        tag = tag_err.mean(1) if self.M else np.zeros(self.B)
        anchor = np.minimum(anchor_err, cfg.error_cap_m).mean(1)
        terms = reward_terms(cfg, tag, anchor, report["calibrating_fraction"], report["round_started"])
        return sum(terms.values()), tag, anchor


def _drift_rows(drift: dict, n: int, rows) -> dict:
    """The odometry snapshot of a cohort (its copies' robots, copy-major) for some of its
    copies (``rows``, increasing): aligned with ``BatchedSystem._robots_of`` of those copies."""
    return {name: v.reshape(-1, n)[np.asarray(rows)].reshape(-1) for name, v in drift.items()}


def _row(array: np.ndarray | None, k: int) -> np.ndarray | None:
    return None if array is None else array[k]
