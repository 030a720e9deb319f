"""Later and first calibrations of many teams at once (the batched env): one compiled loop.

:func:`calibrate_with_priors` solves what :func:`~uwb_env.localization.calibrate_anchors` solves
for a later calibration (``prior`` given, every pair measured), for K teams of N anchors in one
call of ``_lm_kernel.solve_teams_2d``: the same gauge (anchor 0 at the origin, the anchor
farthest from it on +x, per team), the same start (the prior in that gauge), the plain
least-squares stage then the robust one, the same stopping rule, the same chi-square fit
verdict and the same rigid alignment onto the prior. A team is handed back (``None`` in
:func:`calibrate_with_priors`' list, status 0 in a :class:`TeamSolutions`) wherever the full
solver would do more than this one solve: a missing pair, a fit the verdict rejects or a
residual beyond ``restart_sigmas`` (the full solver then restarts, unfolds or rejects
outliers), a step that raises the cost, or no convergence. The caller solves those with
``calibrate_anchors``.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy.special import chdtrc, chdtri

from uwb_env.localization._lm_kernel import LOSS_CODES, solve_teams_2d
from uwb_env.localization.alignment import rigid_align, rigid_align_batch
from uwb_env.measurements import RangeMatrix


@dataclass
class BatchedCalibration:
    """One team's result, with the fields the envs read from a ``CalibrationResult``."""

    positions: np.ndarray
    covariance: np.ndarray
    residuals_m: np.ndarray
    chi2: float
    dof: int
    status: str = "ok"
    ambiguous: bool = False
    cost: float = float("nan")  # the (robust) least-squares cost at the solution

    def anchor_covariance(self) -> np.ndarray:
        n, dim = self.positions.shape
        idx = np.arange(n)
        return self.covariance.reshape(n, dim, n, dim)[idx, :, idx, :]

    @property
    def rms_residual_m(self) -> float:
        return float(np.sqrt(np.mean(self.residuals_m**2)))


STATUS_NONE, STATUS_OK, STATUS_POOR = 0, 1, 2
_STATUS_NAMES = {STATUS_OK: "ok", STATUS_POOR: "poor_fit"}


@dataclass
class TeamSolutions:
    """K teams' solutions as arrays (what the batched env applies without a Python object per
    team). ``status`` per team: 0 handed back to the full solver (nothing else is meaningful
    there), 1 ok, 2 poor fit (returned only where the full solver would end with it too)."""

    positions: np.ndarray  # (K, n, 2)
    covariance: np.ndarray  # (K, 2n, 2n)
    residuals_m: np.ndarray  # (K, P)
    chi2: np.ndarray  # (K,)
    cost: np.ndarray  # (K,) the (robust) least-squares cost at the solution
    status: np.ndarray  # (K,) int
    dof: int

    def __len__(self) -> int:
        return len(self.status)

    def result(self, k: int) -> BatchedCalibration | None:
        if self.status[k] == STATUS_NONE:
            return None
        return BatchedCalibration(self.positions[k], self.covariance[k], self.residuals_m[k], float(self.chi2[k]),
                                  self.dof, _STATUS_NAMES[int(self.status[k])], cost=float(self.cost[k]))

    def results(self) -> list[BatchedCalibration | None]:
        return [self.result(k) for k in range(len(self))]

    def hand_back(self, rows) -> None:
        self.status[rows] = STATUS_NONE

    def subset(self, rows: np.ndarray) -> TeamSolutions:
        return TeamSolutions(self.positions[rows], self.covariance[rows], self.residuals_m[rows], self.chi2[rows],
                             self.cost[rows], self.status[rows], self.dof)


def calibrate_with_priors(matrices: list[RangeMatrix], priors: np.ndarray, range_std_m: float,
                          loss: str = "huber", f_scale: float = 3.0, gauge: str = "prior",
                          max_iterations: int = 50, fit_alpha: float = 1e-3,
                          restart_sigmas: float = 8.0) -> list[BatchedCalibration | None]:
    """2D later calibrations of K teams; ``priors`` (K, N, 2). See the module docstring."""
    out: list[BatchedCalibration | None] = [None] * len(matrices)
    if not matrices:
        return out
    complete, pairs, dist, var = symmetric_arrays(np.stack([m.mean_m for m in matrices]),
                                                  np.stack([m.count for m in matrices]), range_std_m)
    full = np.flatnonzero(complete)
    if not len(full):
        return out
    solved = _solve_teams(pairs, dist[full], var[full], priors[full], loss, f_scale, gauge, max_iterations,
                          fit_alpha, restart_sigmas)
    for r, res in zip(full, solved.results(), strict=True):
        out[r] = res
    return out


def later_calibrations(pairs: np.ndarray, dist: np.ndarray, var: np.ndarray, prior: np.ndarray,
                       loss: str = "huber", f_scale: float = 3.0, gauge: str = "prior",
                       max_iterations: int = 50, fit_alpha: float = 1e-3, restart_sigmas: float = 8.0,
                       poor_fit_prior_std_m: np.ndarray | None = None) -> TeamSolutions:
    """Later calibrations of K complete 2D teams from arrays (``calibrate_with_priors``): the
    fits the verdict accepts (status 1); the other teams are handed back (status 0).

    Poor fits: by default every poor fit is handed back to the full solver (the single env: its
    answers are the full solver's). With ``poor_fit_prior_std_m`` (K, N) (the batched env, where
    15-20 % of 4-anchor rounds fit poorly and one full solve per copy in Python costs most of a
    step) the poor fits with fewer than 3 dof and gauge ``prior`` take the full solver's steps
    here, batched (:func:`_poor_fit_steps`), and come back with its answer where these steps
    reach it; the rest are handed back."""
    args = (loss, f_scale, gauge, max_iterations, fit_alpha, restart_sigmas)
    fast = poor_fit_prior_std_m is not None
    solved = _solve_teams(pairs, dist, var, prior, *args, accept_poor=fast)
    poor = np.flatnonzero(solved.status == STATUS_POOR)
    if not len(poor):
        return solved
    if solved.dof >= 3 or gauge != "prior":  # the full solver would reject outliers / align about anchor 0
        solved.hand_back(poor)
        return solved
    _poor_fit_steps(solved, poor, pairs, dist, var, prior, poor_fit_prior_std_m, args)
    return solved


def _poor_fit_steps(solved: TeamSolutions, poor: np.ndarray, pairs, dist, var, prior, prior_std, args) -> None:
    """The full solver's answer to a later calibration whose solve from the prior fits poorly,
    for the teams ``poor`` of ``solved`` (in place), with at most 2 dof (no outlier rejection):

    1. solve from the ranges alone, trilateration and MDS (``calibration._cold_starts``), each
       placed onto the prior (rigid, reflection allowed);
    2. pick the lowest score, cost plus the prior's chi-square (``_Problem.select`` with a
       prior); where the ranges alone (the lowest cost) prefer a clearly different shape with
       a lower chi-square the full solver flags the round ambiguous: handed back;
    3. a pick that fits is the answer; a poor one is unfolded (:func:`_unfold`, the full
       solver's passes of single-anchor reflections).

    Every start is solved with the full solver's iterations (damped, in the prior's gauge).
    Where one of them does not converge here the full solver would still score it (it keeps
    unconverged candidates): that team is handed back, as is an ambiguous one (the result
    carries no ambiguity flag)."""
    loss, f_scale, gauge, max_iterations, fit_alpha, _ = args
    # the full solver's candidates fit by the p-value alone (``restart_sigmas`` only decides
    # whether it restarts, which a poor fit here already did)
    args = (loss, f_scale, gauge, max_iterations, fit_alpha, np.inf)
    weight = 2.0 / prior_std[poor] ** 2  # dim / std^2, as the full solver's prior term
    target = prior[poor]
    tol = 3.0 * np.sqrt(var[poor].max(1))  # ``_same_shape``'s tolerance
    # every start is solved in the prior's gauge (anchor 0, the anchor farthest from it), as the
    # full solver does: the covariance of a solution depends on the gauge it is computed in
    far = np.argmax(np.linalg.norm(target - target[:, :1], axis=2), axis=1)

    def candidates(starts: np.ndarray, rows: np.ndarray) -> tuple[TeamSolutions, np.ndarray, np.ndarray]:
        """Solve ``starts`` (S, n, 2), start s for team ``rows[s]`` of ``poor``, each placed
        onto its prior (rigid, reflection allowed) as the full solver scores it. Returns the
        solutions, their scores (cost + the prior's chi-square) (S,) and (S,) True where a
        finite start did not converge here (a candidate the full solver has and this solve
        does not: its team goes back)."""
        sol = _solve_in_gauge(pairs, dist[poor][rows], var[poor][rows], starts, far[rows], *args, accept_poor=True,
                              damped=True, onto=target[rows])
        lost = (sol.status == STATUS_NONE) & np.isfinite(starts).all(axis=(1, 2))
        return sol, _scores(sol, target[rows], weight[rows]), lost

    k = len(poor)
    idx = np.arange(k)
    # 1-2: the candidates in the full solver's order (prior, trilateration, MDS); ties keep the first
    mine = solved.subset(poor)
    if solved.dof > 0:
        with np.errstate(invalid="ignore"):
            mine.status[chdtrc(solved.dof, mine.chi2) >= fit_alpha] = STATUS_OK
    tri = _trilateration_starts(pairs, dist[poor])
    mds, top = _mds(pairs, dist[poor])
    mds[~(top[:, 1] > 1e-9 * top[:, 0])] = np.nan  # ``classical_mds``: a flat start is no start
    cold, cold_scores, lost = candidates(np.concatenate([tri, mds]), np.tile(idx, 2))
    # no cold start at all: the full solver lifts a flat MDS start (``mds+lift``): handed back
    flat = np.isnan(tri).any(axis=(1, 2)) & np.isnan(mds).any(axis=(1, 2))
    unknown = lost.reshape(2, k).any(0) | flat
    cands = _stack([mine, cold])
    scores = np.concatenate([_scores(mine, target, weight)[None], cold_scores.reshape(2, k)])  # (3, k)
    pick = np.argmin(scores, axis=0) * k + idx
    by_cost = np.argmin(np.where(cands.status != STATUS_NONE, cands.cost, np.inf).reshape(3, k), axis=0) * k + idx
    apart = np.abs(cands.positions[pick] - cands.positions[by_cost]).max(axis=(1, 2)) > tol
    ambiguous = (cands.chi2[by_cost] < cands.chi2[pick]) & apart
    chosen = cands.subset(pick)
    # 3: a poor pick is unfolded as the full solver does it
    unknown |= _unfold(chosen, scores.min(0), candidates, pairs, var[poor], args[4])
    for f in _ARRAY_FIELDS:
        getattr(solved, f)[poor] = getattr(chosen, f)
    solved.hand_back(poor[ambiguous | unknown])


def _unfold(best: TeamSolutions, best_score: np.ndarray, candidates, pairs, var, fit_alpha) -> np.ndarray:
    """``calibration._Problem.unfold`` for many teams, in place on ``best`` / ``best_score``:
    up to two passes; in each, the anchors in decreasing order of their misfit (their pairs'
    squared whitened residuals, at the pass's start), each mirrored across the line through its
    two nearest others *in the current best* and solved, a lower score replacing the best at
    once; a team stops when its best fits, or after a pass without a gain. The full solver's
    shortcut too: no unfold where even the worst anchors' misfits could not bring the
    chi-square under the fit threshold. Returns (K,) True where a reflection could not be
    solved here (not converged: a candidate the full solver has and this solve does not)."""
    k_teams, n = best.positions.shape[:2]
    unknown = np.zeros(k_teams, dtype=bool)
    active = np.flatnonzero(best.status == STATUS_POOR)
    if n <= 3 or not len(active):  # ``_reflect_anchor``: no line through two others to mirror across
        return unknown
    top = min(n, 16)
    incidence = np.zeros((len(pairs), n))
    incidence[np.arange(len(pairs)), pairs[:, 0]] = 1.0
    incidence[np.arange(len(pairs)), pairs[:, 1]] = 1.0

    def misfit(rows):
        return (best.residuals_m[rows] ** 2 / var[rows]) @ incidence

    if best.dof > 0:
        worst = -np.sort(-misfit(active), axis=1)[:, :top].sum(1)
        explained = ~np.isfinite(best.chi2[active]) | (
            2.0 * worst >= best.chi2[active] - chdtri(best.dof, fit_alpha))
        active = active[explained]
    for _ in range(2):
        if not len(active):
            break
        order = np.argsort(-misfit(active), axis=1)[:, :top]
        improved = np.zeros(len(active), dtype=bool)
        nxt = np.zeros(len(active), dtype=int)  # the next position in ``order`` to try
        live = np.ones(len(active), dtype=bool)  # positions left and no fit yet
        while live.any():
            # The reflections of one best are independent: solve every remaining one at once,
            # and take the first (in misfit order) that scores lower, as the sequential loop
            # would; the ones after it are solved again from the new best.
            sel = np.flatnonzero(live)
            counts = top - nxt[sel]
            team = np.repeat(sel, counts)
            pos = np.concatenate([np.arange(nxt[t], top) for t in sel])
            rows = active[team]
            starts, valid = _reflect_each(best.positions[rows], order[team, pos])
            sol, score, lost = candidates(starts[valid], rows[valid])
            gain = np.zeros(len(team), dtype=bool)
            gain[valid] = score < best_score[rows[valid]] - 1e-9
            full_lost = np.zeros(len(team), dtype=bool)
            full_lost[valid] = lost
            # per team: the first position that gains; what was tried before it counts as tried
            first = np.full(len(sel), top)
            np.minimum.at(first, np.searchsorted(sel, team[gain]), pos[gain])
            tried = pos <= first[np.searchsorted(sel, team)]
            np.logical_or.at(unknown, active[team[tried & full_lost]], True)
            won = first < top
            if won.any():
                take = np.flatnonzero(gain & (pos == first[np.searchsorted(sel, team)]))  # one per winning team
                solved_at = np.cumsum(valid) - 1
                w_rows = rows[take]
                for f in _ARRAY_FIELDS:
                    getattr(best, f)[w_rows] = getattr(sol, f)[solved_at[take]]
                best_score[w_rows] = score[solved_at[take]]
                improved[sel[won]] = True
            nxt[sel] = np.where(won, first + 1, top)
            fits = np.zeros(len(sel), dtype=bool)
            fits[won] = best.status[active[sel[won]]] == STATUS_OK
            live[sel] = (nxt[sel] < top) & ~fits
            done_fit = sel[fits]
            improved[done_fit] = False  # a fitting team leaves the passes
            live[done_fit] = False
        active = active[improved]
    return unknown


def _reflect_each(x: np.ndarray, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``calibration._reflect_anchor`` for many teams (T, N, 2), anchor k[t] of team t:
    (starts (T, N, 2), valid (T,) False where the line through its two nearest is undefined)."""
    t = np.arange(len(x))
    d = np.linalg.norm(x - x[t, k][:, None], axis=2)
    d[t, k] = np.inf
    near = np.argsort(d, axis=1)[:, :2]
    base = x[t, near[:, 0]]
    tangent = x[t, near[:, 1]] - base
    norm = np.linalg.norm(tangent, axis=1)
    valid = norm >= 1e-9
    normal = np.stack([-tangent[:, 1], tangent[:, 0]], 1) / np.where(valid, norm, 1.0)[:, None]
    out = x.copy()
    out[t, k] = x[t, k] - 2.0 * ((x[t, k] - base) * normal).sum(1)[:, None] * normal
    return out, valid


_ARRAY_FIELDS = ("positions", "covariance", "residuals_m", "chi2", "cost", "status")


def _stack(parts: list[TeamSolutions]) -> TeamSolutions:
    return TeamSolutions(*(np.concatenate([getattr(p, f) for p in parts]) for f in _ARRAY_FIELDS), parts[0].dof)


def _scores(sol: TeamSolutions, target: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """What the full solver's starts compete on: cost + 0.5 * sum(weight * |x - prior|^2)
    (solutions already placed onto the prior); inf where not solved."""
    d2 = ((sol.positions - target) ** 2).sum(2)
    return np.where(sol.status != STATUS_NONE, sol.cost + 0.5 * (d2 * weight).sum(1), np.inf)


def _trilateration_starts(pairs: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """(K, n, 2) the full solver's trilateration start (``calibration._trilaterate_2d``) of
    each complete matrix, for all at once; NaN where it raises (the solve hands a NaN start
    back): anchors 0 and 1 closer than 1e-3 of the largest range, or every anchor on their line."""
    k_teams, n = dist.shape[0], int(pairs.max()) + 1
    full = np.zeros((k_teams, n, n))
    full[:, pairs[:, 0], pairs[:, 1]] = dist
    full[:, pairs[:, 1], pairs[:, 0]] = dist
    t = np.arange(k_teams)
    d01 = full[:, 0, 1]
    scale = full.max(axis=(1, 2))
    bad = ~(d01 >= 1e-3 * scale)
    d01 = np.where(bad, 1.0, d01)[:, None]
    d0sq = full[:, 0] * full[:, 0]
    xs = (d0sq - full[:, 1] * full[:, 1] + d01 * d01) / (2 * d01)
    ys = np.sqrt(np.maximum(d0sq - xs * xs, 0.0))
    xs[:, 0], xs[:, 1] = 0.0, d01[:, 0]
    ys[:, :2] = 0.0
    bad |= ~(ys[:, 2:].max(1) >= 1e-6 * scale)
    if n > 3:  # the mirror candidate that better fits the range to the anchor farthest off the axis
        ref = 2 + np.argmax(ys[:, 2:], axis=1)
        dx = xs - xs[t, ref][:, None]
        y_ref, r_ref = ys[t, ref][:, None], full[t, ref]
        flip = np.abs(np.hypot(dx, ys + y_ref) - r_ref) < np.abs(np.hypot(dx, ys - y_ref) - r_ref)
        flip[:, :2] = False
        flip[t, ref] = False
        ys[flip] *= -1.0
    if n > 4:  # second pass: the sign that best fits the ranges to all others as placed
        placed = xs + 1j * ys
        up = xs + 1j * np.abs(ys)
        diag = np.arange(n)
        misfit_up = np.abs(up[:, :, None] - placed[:, None, :]) - full
        misfit_down = np.abs(up.conj()[:, :, None] - placed[:, None, :]) - full
        misfit_up[:, diag, diag] = 0.0
        misfit_down[:, diag, diag] = 0.0
        sign = np.where((misfit_down**2).sum(2) < (misfit_up**2).sum(2), -1.0, 1.0)
        sign[:, :2] = 1.0
        sign[t, ref] = 1.0
        ys = np.abs(ys) * sign
    out = np.stack([xs, ys], axis=2)
    out[bad] = np.nan
    return out


def _mds(pairs: np.ndarray, dist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Classical MDS (2D) of complete matrices: starts (K, n, 2) and the two largest
    eigenvalues of the Gram matrices (K, 2), largest first."""
    k_teams = dist.shape[0]
    n = int(pairs.max()) + 1
    d2 = np.zeros((k_teams, n, n))
    d2[:, pairs[:, 0], pairs[:, 1]] = dist**2
    d2[:, pairs[:, 1], pairs[:, 0]] = dist**2
    centre = np.eye(n) - 1.0 / n
    values, vectors = np.linalg.eigh(-0.5 * centre @ d2 @ centre)  # ascending
    top = values[:, -2:][:, ::-1]
    return vectors[:, :, -2:][:, :, ::-1] * np.sqrt(np.maximum(top, 0.0))[:, None, :], top


@lru_cache(maxsize=64)
def _upper_pairs(n: int) -> tuple[np.ndarray, np.ndarray]:
    """``np.triu_indices(n, 1)``, built once per team size (read-only: shared by every call)."""
    iu, ju = np.triu_indices(n, 1)
    iu.flags.writeable = ju.flags.writeable = False
    return iu, ju


def symmetric_arrays(mean_m: np.ndarray, count: np.ndarray, range_std_m: float,
                     carry_var_m2: np.ndarray | None = None):
    """``RangeMatrix.complete_symmetric(std_m=range_std_m)`` for (K, N, N) means and counts at
    once (and the matrices' (K, N, N) ``carry_var_m2``, or None): (complete (K,) bool, pairs
    (P, 2), dist (K, P), var (K, P)); a team is complete when every ordered pair was measured
    with a finite mean >= the solver's negative tolerance."""
    from uwb_env.measurements import combine_directions, negative_range_floor_m

    n = mean_m.shape[1]
    iu, ju = _upper_pairs(n)
    ma, mb = mean_m[:, iu, ju], mean_m[:, ju, iu]
    ca, cb = count[:, iu, ju].astype(float), count[:, ju, iu].astype(float)
    # each direction against its own floor (carried ranges: the carry's error too)
    floor_a = negative_range_floor_m(None if carry_var_m2 is None else carry_var_m2[:, iu, ju])
    floor_b = negative_range_floor_m(None if carry_var_m2 is None else carry_var_m2[:, ju, iu])
    with np.errstate(invalid="ignore"):
        complete = ((np.minimum(ca, cb) > 0).all(1) & (ma >= floor_a).all(1) & (mb >= floor_b).all(1)
                    & (np.maximum(ma, mb) < np.inf).all(1))
    info_a, info_b = ca / range_std_m**2, cb / range_std_m**2
    with np.errstate(invalid="ignore", divide="ignore"):  # incomplete teams: NaN / inf, not used
        carry = () if carry_var_m2 is None else (carry_var_m2[:, iu, ju], carry_var_m2[:, ju, iu])
        dist, var = combine_directions(ma, mb, info_a, info_b, *carry)
    return complete, np.column_stack([iu, ju]), dist, var


def first_calibrations(pairs: np.ndarray, dist: np.ndarray, var: np.ndarray, loss: str = "huber",
                       f_scale: float = 3.0, max_iterations: int = 50, fit_alpha: float = 1e-3,
                       restart_sigmas: float = 8.0, min_aspect: float = 0.1) -> TeamSolutions:
    """First calibrations (no prior) of K complete 2D teams: classical MDS of each team's
    matrix as the start, then :func:`calibrate_with_priors`' solve and verdict. Positions and
    covariance come back as the full solver's first calibration gives them: in the paper's
    frame (anchor 0 at the origin, anchor 1 on +x, the y axis to the side where the other
    anchors' y sum positive), with that gauge's covariance. A poor fit is returned as such
    (``status`` poor) where the full solver would end with it too: too few degrees of
    freedom to reject a pair and no single-anchor reflection with a lower cost. A team is handed
    back (status 0) where the full solver's several starts could matter: a thin or degenerate
    layout (second MDS eigenvalue below ``min_aspect`` of the first), a poor fit it would work
    on further, or anything :func:`calibrate_with_priors` hands back."""
    n = int(pairs.max()) + 1
    start, top = _mds(pairs, dist)
    # thin or degenerate layouts get no start (the kernel hands a NaN start back)
    start[~((top[:, 1] > 0) & (top[:, 1] >= min_aspect * top[:, 0]))] = np.nan
    # the full solver's first-calibration gauge: anchor 0 at the origin, anchor 1 on +x
    args = (loss, f_scale, "paper", max_iterations, fit_alpha, restart_sigmas)
    solved = _solve_in_gauge(pairs, dist, var, start, np.ones(len(start), dtype=np.int64), *args, accept_poor=True)
    poor = np.flatnonzero(solved.status == STATUS_POOR)
    if len(poor) and solved.dof < 3:
        # What the full solver does with a poor fit it cannot reject a pair from (fewer than two
        # dof would be left): it reflects each anchor across the line through its two nearest
        # others and keeps a lower cost. Where no reflection lowers the cost its answer is this
        # one; where one does, hand the team back.
        best = solved.cost[poor]
        starts = _reflections(solved.positions[poor])  # one batched solve
        cand = _solve_in_gauge(pairs, np.tile(dist[poor], (n, 1)), np.tile(var[poor], (n, 1)), starts,
                               np.ones(len(starts), dtype=np.int64), *args, accept_poor=True)
        costs = np.where(cand.status != STATUS_NONE, cand.cost, np.inf).reshape(n, -1)
        solved.hand_back(poor[(costs < best - 1e-9).any(0)])
    elif len(poor):  # the full solver would try outlier rejection: hand back
        solved.hand_back(poor)
    return solved


def _reflections(x: np.ndarray) -> np.ndarray:
    """(N * T, N, 2): for k = 0..N-1 in turn, every team (T, N, 2) with anchor k mirrored across
    the line through its two nearest others (``calibration._reflect_anchor`` for many teams and
    every anchor at once; unlike it, also where that line is undefined or N <= 3: such a start
    only costs a solve, and a worse candidate never replaces the answer)."""
    k_teams, n, _ = x.shape
    d = np.linalg.norm(x[:, :, None] - x[:, None, :], axis=3)  # (T, N, N)
    d[:, np.arange(n), np.arange(n)] = np.inf
    near = np.argsort(d, axis=2)[:, :, :2]  # (T, N, 2)
    t = np.arange(k_teams)[:, None]
    base, other = x[t, near[..., 0]], x[t, near[..., 1]]  # (T, N, 2) each
    tangent = other - base
    normal = np.stack([-tangent[..., 1], tangent[..., 0]], -1) / np.maximum(
        np.linalg.norm(tangent, axis=-1), 1e-12)[..., None]
    mirrored = x - 2.0 * ((x - base) * normal).sum(-1)[..., None] * normal  # (T, N, 2): anchor k's mirror
    out = np.repeat(x[None], n, axis=0)  # (N, T, N, 2)
    idx = np.arange(n)
    out[idx, :, idx] = mirrored.transpose(1, 0, 2)
    return out.reshape(n * k_teams, n, 2)


def _solve_teams(pairs, dist, var, prior, loss, f_scale, gauge, max_iterations, fit_alpha, restart_sigmas,
                 accept_poor=False) -> TeamSolutions:
    """The solve of :func:`calibrate_with_priors` on arrays, in the full solver's gauge: anchor 0
    at the origin, the anchor farthest from it on +x."""
    far = np.argmax(np.linalg.norm(prior - prior[:, :1], axis=2), axis=1)
    return _solve_in_gauge(pairs, dist, var, prior, far, loss, f_scale, gauge, max_iterations, fit_alpha,
                        restart_sigmas, accept_poor)


def _solve_in_gauge(pairs, dist, var, prior, ref, loss, f_scale, gauge, max_iterations, fit_alpha, restart_sigmas,
                 accept_poor=False, damped=False, onto=None) -> TeamSolutions:
    """One compiled solve of every team from ``prior`` in the gauge (anchor 0, anchor ref[k])
    (``_lm_kernel.solve_teams_2d``), the fit verdict, and the gauge's placement; ``accept_poor``:
    converged fits the verdict rejects come back as poor instead of handed back; ``onto``
    (gauge ``prior``): the positions the solutions are placed onto, if not their starts."""
    k_teams, n, dim = prior.shape
    i = np.ascontiguousarray(pairs[:, 0], dtype=np.int64)
    j = np.ascontiguousarray(pairs[:, 1], dtype=np.int64)
    sqrt_iv = 1.0 / np.sqrt(var)
    x, ok, res, chi2, zmax, cost, cov, good = solve_teams_2d(
        np.ascontiguousarray(prior, dtype=np.float64), np.ascontiguousarray(ref, dtype=np.int64), i, j,
        np.ascontiguousarray(dist, dtype=np.float64), np.ascontiguousarray(sqrt_iv, dtype=np.float64),
        LOSS_CODES[loss], float(f_scale), int(max_iterations), bool(damped))
    dof = len(pairs) - (n * dim - 3)
    with np.errstate(invalid="ignore"):
        p_value = chdtrc(dof, chi2) if dof > 0 else np.ones(k_teams)
        fit = ok & (p_value >= fit_alpha) & (zmax <= restart_sigmas)
    status = np.where(fit, STATUS_OK, STATUS_POOR).astype(np.int8)
    status[~(ok & good & (fit | accept_poor))] = STATUS_NONE
    rows = np.flatnonzero(status != STATUS_NONE)
    positions = np.full_like(x, np.nan)
    if len(rows):
        xs, cs = x[rows], cov[rows]
        if gauge == "paper":  # the first calibration's sign rule on the gauge solution (an axis flip)
            flip = np.where(xs[:, :, 1].sum(1) < 0, -1.0, 1.0)
            positions[rows] = xs * np.stack([np.ones_like(flip), flip], 1)[:, None, :]
            signs = np.tile(np.stack([np.ones_like(flip), flip], 1), (1, n))
            cov[rows] = cs * signs[:, :, None] * signs[:, None, :]
        elif gauge == "anchor0":  # rotation about anchor 0: one alignment per team
            for r, k in enumerate(rows):
                rot, trans = rigid_align(xs[r], prior[k], allow_reflection=True, pivot=0)
                positions[k] = xs[r] @ rot.T + trans
                cov[k] = _rotate(cs[r][None], rot[None], n, dim)[0]
        else:
            rot, trans = rigid_align_batch(xs, (prior if onto is None else onto)[rows])
            positions[rows] = np.einsum("knj,kij->kni", xs, rot) + trans[:, None]
            cov[rows] = _rotate(cs, rot, n, dim)
    return TeamSolutions(positions, cov, res, chi2, cost, status, dof)


def _rotate(cov: np.ndarray, rot: np.ndarray, n: int, dim: int) -> np.ndarray:
    """(K, n*dim, n*dim) covariances of points rotated by (K, dim, dim): blockwise R C R^T, as
    B C B^T with B the block-diagonal of R (two batched matmuls)."""
    k_teams = len(cov)
    blocks = np.zeros((k_teams, n, dim, n, dim))
    idx = np.arange(n)
    blocks[:, idx, :, idx, :] = rot[None]
    blocks = blocks.reshape(k_teams, n * dim, n * dim)
    return blocks @ cov @ blocks.transpose(0, 2, 1)
