"""What B teams know of their anchors and tags, and what a finished team round does to it.

One implementation for both systems: :class:`~uwb_env.system.LocalizationSystem` holds a batch
of one (its attributes are views of row 0), :class:`~uwb_env.batch.BatchedSystem` a batch of B.

- :class:`TeamState`: the calibration bookkeeping (covariances, counters, the last fit's RMS),
  the tag tracks (fix, velocity, age, status) and the residual ring buffers the features read;
  :meth:`TeamState.apply_calibrations` puts team solutions in place, :meth:`TeamState.record_tag_fixes`
  and :meth:`TeamState.hold_tags` move the tag tracks on.
- :func:`solve_later_rounds`: a later team round's solve for C teams at once: the compiled
  batched solve for the usual case (2D, every pair, a fit the verdict accepts), the full
  solver (all its starts and checks) for whatever it hands back.

Free of RL APIs, like the systems.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from uwb_env.localization import GeometryError, LocalizationError, calibrate_anchors
from uwb_env.localization.batched_calibration import (
    STATUS_NONE,
    STATUS_POOR,
    TeamSolutions,
    later_calibrations,
    symmetric_arrays,
)
from uwb_env.localization.multilateration import TAG_NO_FIX
from uwb_env.measurements import RangeMatrix

# CalibrationResult.status values, in the order of the ``calibration_fit`` code
CALIBRATION_FIT_NAMES = ("ok", "poor_fit", "not_converged")
FIT_OK, FIT_POOR, FIT_NOT_CONVERGED, FIT_ERROR = 0, 1, 2, -1


class RoundSolutions:
    """C teams' round outcomes as arrays (no Python object per team on the batched path).

    ``fit`` per team: a ``CALIBRATION_FIT_NAMES`` index, or ``FIT_ERROR`` (the solver raised:
    ``message`` says why; nothing else is meaningful there). ``positions`` (C, N, dim),
    ``anchor_cov`` (C, N, dim, dim) the per-anchor blocks of the solution's covariance, ``chi2``,
    ``dof``, ``rms_m`` (C,), ``ambiguous`` (C,); ``compiled`` (C,) the answer came from the
    compiled batched solve (the rest: the full solver).
    """

    def __init__(self, n_teams: int, n_anchors: int, dim: int):
        self.fit = np.full(n_teams, FIT_ERROR)
        self.positions = np.full((n_teams, n_anchors, dim), np.nan)
        self.anchor_cov = np.full((n_teams, n_anchors, dim, dim), np.nan)
        self.chi2 = np.zeros(n_teams)
        self.dof = np.zeros(n_teams, dtype=int)
        self.rms_m = np.zeros(n_teams)
        self.ambiguous = np.zeros(n_teams, dtype=bool)
        self.compiled = np.zeros(n_teams, dtype=bool)
        self.message: list[str | None] = [None] * n_teams

    @property
    def applicable(self) -> np.ndarray:
        """(C,) a shape to apply: ok or a poor fit (a fit that did not converge is not)."""
        return (self.fit == FIT_OK) | (self.fit == FIT_POOR)

    @property
    def chi2_per_dof(self) -> np.ndarray:
        return np.where(self.dof > 0, self.chi2 / np.maximum(self.dof, 1), 0.0)

    def put_solved(self, rows: np.ndarray, solved: TeamSolutions) -> None:
        """The compiled solve's answers (status ok or poor fit) for ``rows``."""
        c, n = len(rows), solved.positions.shape[1]
        idx = np.arange(n)
        self.positions[rows] = solved.positions
        self.anchor_cov[rows] = solved.covariance.reshape(c, n, 2, n, 2).transpose(0, 1, 3, 2, 4)[:, idx, idx]
        self.fit[rows] = np.where(solved.status == STATUS_POOR, FIT_POOR, FIT_OK)
        self.chi2[rows] = solved.chi2
        self.dof[rows] = solved.dof
        r2 = solved.residuals_m**2  # np.mean's sum and division without its ~10 us of overhead
        self.rms_m[rows] = np.sqrt(np.add.reduce(r2, axis=1) / r2.shape[1])
        self.ambiguous[rows] = False
        self.compiled[rows] = True

    def put_result(self, row: int, result) -> None:
        """A full solver's ``CalibrationResult`` (a ``degenerate`` one is not a shape to apply:
        recorded as the error the solver raised for it before it reported the fit)."""
        if result.status == "degenerate":
            self.put_error(row, GeometryError(result.message))
            return
        self.positions[row] = result.positions
        self.anchor_cov[row] = result.anchor_covariance()
        self.fit[row] = CALIBRATION_FIT_NAMES.index(result.status)
        self.chi2[row], self.dof[row] = result.chi2, result.dof
        self.rms_m[row] = result.rms_residual_m
        self.ambiguous[row] = bool(result.ambiguous)
        if result.status == "not_converged":
            self.message[row] = f"calibration not converged: {result.message}"

    def put_error(self, row: int, err: Exception) -> None:
        self.fit[row] = FIT_ERROR
        self.message[row] = f"{type(err).__name__}: {err}"

    def with_heights(self, heights_m: np.ndarray, height_std_m: float) -> RoundSolutions:
        """These planar (dim 2) solutions as 3D ones with the given (C, N) heights, each known to
        ``height_std_m`` and independent of the plane (``SimConfig.known_heights_std_m``)."""
        c, n, dim = self.positions.shape
        if dim != 2:
            raise ValueError(f"with_heights needs planar solutions, got dim={dim}")
        out = RoundSolutions(c, n, 3)
        for name in ("fit", "chi2", "dof", "rms_m", "ambiguous", "compiled"):
            setattr(out, name, getattr(self, name).copy())
        out.message = list(self.message)
        out.positions[..., :2] = self.positions
        out.positions[..., 2] = heights_m
        out.anchor_cov[:] = 0.0
        out.anchor_cov[..., :2, :2] = self.anchor_cov
        out.anchor_cov[..., 2, 2] = height_std_m**2
        return out


def solve_later_rounds(mean: np.ndarray, std: np.ndarray, count: np.ndarray, carry_var_m2: np.ndarray | None,
                       est_mid: np.ndarray, prior_std_m: np.ndarray, solver, pair_range_std_m: float) -> RoundSolutions:
    """Later team rounds of C teams: bias-corrected pair means carried to each round's midpoint
    ``mean`` (C, N, N), their ``std`` and ``count`` (C, N, N), the carry variance (C, N, N) or
    None; ``est_mid`` (C, N, dim) the estimates at the midpoint (the prior and the gauge),
    ``prior_std_m`` (C, N); ``solver`` a :class:`~uwb_env.config.SolverConfig`.

    2D teams with every pair go to the compiled batched solve (``later_calibrations``; its poor
    fits of 3-4 anchors take the full solver's further steps batched, tested equal to it); what
    it hands back (missing pairs, a rejected fit it can work on, an ambiguous shape) and every
    3D team go to the full solver."""
    n_teams, n, dim = est_mid.shape
    out = RoundSolutions(n_teams, n, dim)
    if dim == 2:
        complete, pairs, dist, var = symmetric_arrays(mean, count, pair_range_std_m, carry_var_m2)
        rows = np.flatnonzero(complete)
        if len(rows):
            solved = later_calibrations(pairs, dist[rows], var[rows], est_mid[rows], solver.loss,
                                        solver.f_scale_sigmas, solver.gauge, poor_fit_prior_std_m=prior_std_m[rows])
            done = solved.status != STATUS_NONE
            if done.any():
                out.put_solved(rows[done], solved.subset(done))
    for row in np.flatnonzero(~out.compiled):
        try:
            matrix = RangeMatrix(mean[row], std[row], count[row], None if carry_var_m2 is None else carry_var_m2[row])
            result = calibrate_anchors(matrix, dim=dim, prior=est_mid[row], gauge=solver.gauge, loss=solver.loss,
                                       f_scale=solver.f_scale_sigmas, range_std_m=pair_range_std_m,
                                       prior_std_m=prior_std_m[row])
        except LocalizationError as err:  # e.g. dropouts disconnected the graph: keep odometry, say why
            out.put_error(row, err)
            continue
        out.put_result(row, result)
    return out


@dataclass
class TeamState:
    """B teams of N anchors and M tags in ``dim`` dimensions, (B, ...) arrays."""

    calibration_count: np.ndarray  # (B,) team calibrations applied
    calibrations_poor_fit: np.ndarray  # (B,) of them poor fits
    last_calibration_rms_m: np.ndarray  # (B,)
    time_since_calibration_s: np.ndarray  # (B, N)
    steps_since_calibration: np.ndarray  # (B, N)
    calibration_var_m2: np.ndarray  # (B, N) trace of each anchor's calibration covariance
    anchor_cov: np.ndarray  # (B, N, dim, dim)
    tag_fix: np.ndarray  # (B, M, dim), NaN: no fix yet (with tag_fallback="predict", moved on while held)
    tag_measured: np.ndarray  # (B, M, dim) each tag's last measured fix
    tag_velocity: np.ndarray  # (B, M, dim)
    tag_fix_age_s: np.ndarray  # (B, M) time since each tag's last measured fix
    tag_status: np.ndarray  # (B, M) int8, multilateration.TAG_STATUS_NAMES
    tag_residual_hist: np.ndarray  # (B, W) ring buffer: the tags' mean fix residual per step
    anchor_residual_hist: np.ndarray  # (B, W, N) each anchor's mean range residual per step
    hist_count: np.ndarray  # (B,) steps recorded since the last team calibration

    @classmethod
    def new(cls, n_teams: int, n_anchors: int, n_tags: int, dim: int, window: int) -> TeamState:
        b, n, m = n_teams, n_anchors, n_tags
        return cls(np.zeros(b, dtype=np.int64), np.zeros(b, dtype=np.int64), np.zeros(b), np.zeros((b, n)),
                   np.zeros((b, n)), np.zeros((b, n)), np.zeros((b, n, dim, dim)), np.full((b, m, dim), np.nan),
                   np.full((b, m, dim), np.nan), np.zeros((b, m, dim)), np.zeros((b, m)),
                   np.full((b, m), TAG_NO_FIX, dtype=np.int8),
                   np.zeros((b, window)), np.zeros((b, window, n)), np.zeros(b, dtype=np.int64))

    def __post_init__(self):
        self._team_index = np.arange(len(self.calibration_count))

    @property
    def window(self) -> int:
        return self.tag_residual_hist.shape[1]

    def tick(self, dt_s: float) -> None:
        """One step passed for every team."""
        self.steps_since_calibration += 1
        self.time_since_calibration_s += dt_s

    def apply_calibrations(self, rows: np.ndarray, anchors_est: np.ndarray, solutions: RoundSolutions,
                           which: np.ndarray, since_mid: np.ndarray) -> None:
        """Team calibrations: team ``rows[i]`` takes ``solutions``' team ``which[i]`` (each
        applicable), its estimates (``anchors_est`` (B, N, dim), written in place) the solution
        plus the odometry since the round's midpoint ``since_mid`` (len(rows), N, dim).

        A poor fit (e.g. an NLOS-biased pair the few spare pairs cannot single out) is still the
        best shape the ranges give, but its noise-model covariance is too small: it is scaled by
        the reduced chi-square (the Birge ratio), so the predicted errors say what we know. The
        odometry's drift restart is the caller's (its robots are indexed differently)."""
        fit = solutions.fit[which]
        scale = np.where(fit == FIT_POOR, np.maximum(1.0, solutions.chi2_per_dof[which]), 1.0)
        anchors_est[rows] = solutions.positions[which] + since_mid
        cov = scale[:, None, None, None] * solutions.anchor_cov[which]
        self.anchor_cov[rows] = cov
        self.calibration_var_m2[rows] = np.trace(cov, axis1=2, axis2=3)
        self.last_calibration_rms_m[rows] = solutions.rms_m[which]
        self.calibration_count[rows] += 1
        self.calibrations_poor_fit[rows] += fit == FIT_POOR
        self.time_since_calibration_s[rows] = 0.0
        self.steps_since_calibration[rows] = 0
        # residuals of fixes against the old estimates say nothing about the new ones
        self.hist_count[rows] = 0

    def hold_tags(self, rows, dt_s: float, predict: bool) -> None:
        """No tag fix this step (a round holds the channel): the fixes age, and with ``predict``
        move on at their velocity."""
        self.tag_fix_age_s[rows] += dt_s
        if predict:
            self.tag_fix[rows] += self.tag_velocity[rows] * dt_s

    def record_tag_fixes(self, rows, positions: np.ndarray, rms_m: np.ndarray, tag_residual_m: np.ndarray,
                         anchor_residual_m: np.ndarray, any_fix: np.ndarray, dt_s: float) -> None:
        """This step's tag fixes of teams ``rows`` (a slice or index array): positions (S, M, dim),
        their RMS residual (S, M) (NaN: no fix; the tag keeps its last one and ages), and the
        residual statistics of the fixes (``residual_statistics``: (S,), (S, N), (S,)).

        A tag's velocity is its displacement since its last *measured* fix over the time since
        (held fixes, moved on at the old velocity with ``tag_fallback="predict"``, and steps
        without a fix do not count as measurements). The residual ring buffer of a team without a
        usable fix this step carries its previous entry. (One compiled pass: a step of the single
        env is a few microseconds of arithmetic.)"""
        teams = self._team_index[rows]
        _record_tag_fixes(self.tag_fix, self.tag_measured, self.tag_velocity, self.tag_fix_age_s,
                          self.tag_residual_hist, self.anchor_residual_hist, self.hist_count, teams, positions, rms_m,
                          tag_residual_m, anchor_residual_m, any_fix, float(dt_s))

    def filled(self) -> np.ndarray:
        """(B,) valid slots of the residual ring buffers (from the start)."""
        return np.minimum(self.hist_count, self.window)


@njit(cache=True)
def _record_tag_fixes(tag_fix, measured, velocity, age, tag_hist, anchor_hist, hist_count, teams, positions, rms,
                      tag_mean, anchor_mean, any_fix, dt):
    """:meth:`TeamState.record_tag_fixes` for the teams ``teams`` (S,); ``positions`` etc. row s
    belongs to team ``teams[s]``."""
    dim = tag_fix.shape[2]
    window = tag_hist.shape[1]
    for s in range(len(teams)):
        b = teams[s]
        for m in range(tag_fix.shape[1]):
            a = age[b, m]
            if not np.isfinite(rms[s, m]):  # no fix: keep the last one, older by a step
                age[b, m] = a + dt
                continue
            had = True
            for d in range(dim):
                had = had and np.isfinite(measured[b, m, d])
            elapsed = max(a + dt, dt)
            for d in range(dim):
                if had:
                    velocity[b, m, d] = (positions[s, m, d] - measured[b, m, d]) / elapsed
                tag_fix[b, m, d] = positions[s, m, d]
                measured[b, m, d] = positions[s, m, d]
            age[b, m] = 0.0
        slot = hist_count[b] % window
        prev = (slot - 1 + window) % window
        if any_fix[s]:
            tag_hist[b, slot] = tag_mean[s]
            for k in range(anchor_hist.shape[2]):
                anchor_hist[b, slot, k] = anchor_mean[s, k]
        else:
            tag_hist[b, slot] = tag_hist[b, prev]
            for k in range(anchor_hist.shape[2]):
                anchor_hist[b, slot, k] = anchor_hist[b, prev, k]
        hist_count[b] += 1
