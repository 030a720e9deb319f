"""Anchor autocalibration from inter-anchor ranges (Martinez Almansa et al., Sec. 3).

First calibration (no prior), the paper's rules: anchor 0 at the origin, anchor 1 on +x,
the others in +y (which fixes the reflection: see ``alignment.paper_frame``; in 3D the
anchor farthest off the x axis also fixes the rotation about x). Initial positions by
trilateration from the ranges to anchors 0 and 1; each further anchor's y sign is checked
against its ranges to the anchors already placed, which keeps the paper's solution where its
assumption holds and repairs it where it does not. Classical MDS takes over when
trilateration is ill-posed. Then weighted least squares over every available pair.

Later calibrations (a prior = the anchors' current on-board estimates): only "anchor 0 is the
origin" is assumed. The shape is solved starting from the prior in an internal gauge
(anchor 0 at the origin, the anchor farthest from it on +x, the most off-axis one in +y),
then placed in the running frame:

- ``gauge="anchor0"`` (paper): anchor 0 keeps its prior position; rotation *and reflection*
  are the best orthogonal alignment, about anchor 0, of the solved shape to the prior.
  Reflection is free because ranges cannot tell mirror images apart: the prior decides.
- ``gauge="prior"``: best rigid alignment (translation too) to all anchors' priors, which
  averages the odometry errors of all anchors instead of trusting anchor 0's alone.

The reported covariance is (J^T W J)^-1 in the internal gauge, rotated into the output frame:
it is the uncertainty of the shape with the gauge (anchor 0, the x axis) held fixed.

Right when it says so. Range-only least squares has folded local minima (an anchor mirrored
across a line through others), which a single start can fall into, most often on thin or
near-collinear layouts and with missing pairs. So every solve ends with a goodness-of-fit test
(chi-square of the whitened residuals against the degrees of freedom); the first calibration
always, and a later one whose fit fails, are solved from several starts (trilateration,
classical MDS, SMACOF on the measured pairs only, the prior) and, while the fit still fails,
from single-anchor reflections of the best solution; the lowest cost wins. ``converged`` is True
only when the optimizer converged *and* the fit is explained by the noise (``status``).

Weights: by default each pair's variance is the range model's sigma^2 / K (K = exchanges that
arrived): the sample std of K = 5 ranges is itself noisy, and weighting by it makes the
estimate worse than the bound and its covariance too small (``weighting="sample"`` keeps it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from functools import lru_cache

import numpy as np
from scipy.sparse.csgraph import shortest_path
from scipy.special import chdtrc, chdtri

from uwb_env.localization.alignment import frame_refs, paper_frame, rigid_align
from uwb_env.localization.buildup import buildup_starts
from uwb_env.localization.degenerate import degenerate_fit, shape_beyond_scene
from uwb_env.localization.errors import (
    DisconnectedGraphError,
    GeometryError,
    InvalidRangeError,
    SolverArgumentError,
    TooFewAnchorsError,
)
from uwb_env.localization.pair_solver import PairStructure, pair_structure, solve_pair_ranges
from uwb_env.localization.rigidity import generically_globally_rigid, generically_rigid
from uwb_env.localization.robust import check_loss, robust_cost
from uwb_env.measurements import NEGATIVE_RANGE_TOLERANCE_M, RangeMatrix, _pair_index, negative_range_floor_m

GAUGES = ("anchor0", "prior")
INITIALIZERS = ("auto", "trilateration", "mds")
WEIGHTINGS = ("model", "sample")
STATUSES = ("ok", "poor_fit", "not_converged", "degenerate")


@lru_cache(maxsize=1)
def default_range_std_m() -> float:
    """Std of one bias-corrected range of the fitted DWM1001 model (the default weights)."""
    from uwb_env.sim.ranging import RangeModel  # the fit to the paper's measured data

    return float(RangeModel().corrected_noise_std_m)


@dataclass
class CalibrationResult:
    """Solution of one calibration.

    Attributes:
        positions: (n, dim) anchor positions in the output frame.
        covariance: (n*dim, n*dim) covariance (gauge held fixed; zeros on gauge coordinates).
        pairs: (P, 2) anchor pairs used; ``ranges_m`` their (combined) ranges.
        residuals_m: (P,) fitted minus measured range per pair.
        iterations, cost, converged, message: optimizer diagnostics.
        initializer: "trilateration", "mds", "prior", or "prior+trilateration" / "prior+mds"
            when the prior's solution was replaced by a restart from the ranges alone.
        gauge_refs: anchors fixing the internal gauge (origin, +x, +y[, +z]).
        chi2, dof, fit_p_value: goodness of fit: sum of squared whitened residuals over the
            pairs kept, its degrees of freedom (pairs - free coordinates) and the chi-square
            upper-tail probability (1.0 when dof = 0: nothing to test).
        status: ``ok``; ``poor_fit`` (converged, but the residuals are larger than the noise
            explains at ``fit_alpha``: a folded shape, outliers or a wrong noise model);
            ``not_converged`` (iteration limit or no decrease); ``degenerate`` (the best fit
            leaves one direction fixed only to second order, e.g. three anchors collinear
            within the noise: its covariance there comes from the profile chi-square's one-sigma
            points, see ``localization.degenerate``; not a shape to apply without care).
        optimizer_converged: the optimizer's own verdict, whatever the fit.
        rejected_pairs: (R, 2) pairs left out as outliers (robust mode), empty otherwise.
        starts_tried: number of starts solved.
        ambiguous: another shape, clearly different, fits the ranges as well (within the fit
            test's margin): with a prior the one closest to it was taken, but the ranges alone
            do not decide (e.g. a quadrilateral with a missing diagonal, a near-collinear team).
            Without a prior also when the frame's reflection is uncertain: the rule "the other
            anchors' y (3D: z) sum positive" is within 3 sigma of flipping, so the coordinates
            may be the mirror image of the paper frame's (thin strips with anchors on both
            sides of the line through anchors 0 and 1).
    """

    positions: np.ndarray
    covariance: np.ndarray
    pairs: np.ndarray
    ranges_m: np.ndarray
    residuals_m: np.ndarray
    range_var_m2: np.ndarray
    iterations: int
    cost: float
    converged: bool
    message: str
    initializer: str
    gauge_refs: tuple[int, ...]
    chi2: float = 0.0
    dof: int = 0
    fit_p_value: float = 1.0
    status: str = "ok"
    optimizer_converged: bool = True
    rejected_pairs: np.ndarray = None  # type: ignore[assignment]
    starts_tried: int = 1
    ambiguous: bool = False

    def __post_init__(self):
        if self.rejected_pairs is None:
            self.rejected_pairs = np.zeros((0, 2), dtype=int)

    @property
    def fit_ok(self) -> bool:
        return self.status == "ok"

    @property
    def n_anchors(self) -> int:
        return self.positions.shape[0]

    def anchor_covariance(self) -> np.ndarray:
        """(n, dim, dim) per-anchor covariance blocks."""
        n, dim = self.positions.shape
        idx = np.arange(n)
        return self.covariance.reshape(n, dim, n, dim)[idx, :, idx, :]

    def position_std_m(self) -> np.ndarray:
        """(n,) sqrt of the trace of each anchor's covariance block."""
        return np.sqrt(np.trace(self.anchor_covariance(), axis1=1, axis2=2))

    @property
    def rms_residual_m(self) -> float:
        return float(np.sqrt(np.mean(self.residuals_m**2))) if len(self.residuals_m) else 0.0

    @property
    def normalized_residuals(self) -> np.ndarray:
        return self.residuals_m / np.sqrt(self.range_var_m2)


def calibrate_anchors(
    ranges: RangeMatrix | np.ndarray,
    *,
    dim: int = 2,
    prior: np.ndarray | None = None,
    gauge: str = "anchor0",
    loss: str = "linear",
    f_scale: float = 2.0,
    range_std_m: float | None = None,
    weighting: str = "model",
    min_range_std_m: float = 0.03,
    initializer: str = "auto",
    max_iterations: int = 50,
    restart_sigmas: float = 8.0,
    fit_alpha: float = 1e-3,
    reject_outliers: bool | None = None,
    prior_std_m: float | np.ndarray | None = None,
) -> CalibrationResult:
    """Estimate all anchor positions from a calibration round.

    Args:
        ranges: bias-corrected :class:`RangeMatrix` (per ordered pair mean/std/count), or an
            (n, n) matrix of ranges (NaN = missing): one range per unordered pair, the two
            directions averaged when both are given, each with std ``range_std_m``.
        dim: 2 or 3.
        prior: (n, dim) current on-board estimates; ``None`` for the first calibration.
        gauge: how a later calibration is placed in the running frame (module docstring).
        loss: ``linear``, ``huber``, ``soft_l1`` or ``cauchy`` (robust to NLOS outliers).
        f_scale: robust-loss scale in units of the range std (2 = start down-weighting at 2 sigma).
        range_std_m: std of one range; default: the fitted DWM1001 model's (``default_range_std_m``).
        weighting: ``model`` (default): a pair's variance is range_std_m^2 / K; ``sample``: the
            pair's sample std (floored at ``min_range_std_m``) squared over K.
        min_range_std_m: floor on the sample std (``weighting="sample"``).
        initializer: ``auto`` (every start, lowest cost), ``trilateration`` or ``mds`` (that start
            first; the others still run when its fit fails).
        max_iterations: Gauss-Newton / Levenberg-Marquardt iterations per start (``pair_solver``).
        restart_sigmas: with a prior, a whitened residual above this also triggers the restarts.
        fit_alpha: significance of the chi-square fit test (``status``).
        reject_outliers: drop pairs whose residual the noise cannot explain, one at a time, while
            the shape stays rigid (``rejected_pairs``). Default: on for robust losses.
        prior_std_m: scalar or (n,) std of each prior position's error (sqrt of the trace of its
            covariance). When several starts give different shapes, the one with the lowest
            chi-square of ranges *plus* prior (after rigid alignment to the prior) wins: with few
            pairs an NLOS outlier can make a fold fit the ranges better than the true shape, and
            a prior known to 10 cm rules out a shape 60 cm away. Without it, the ranges decide.

    Raises:
        TooFewAnchorsError, InvalidRangeError, DisconnectedGraphError, GeometryError (all
        LocalizationError); SolverArgumentError for arguments out of their domain.
    """
    check_loss(loss)
    _check_arguments(gauge, initializer, dim, weighting, f_scale, max_iterations, restart_sigmas, fit_alpha,
                     min_range_std_m, range_std_m)
    if range_std_m is None and weighting == "model":
        range_std_m = default_range_std_m()
    if reject_outliers is None:
        reject_outliers = loss != "linear"
    pairs, dist, var, n = _pair_data(ranges, range_std_m if weighting == "model" else None, min_range_std_m)
    if n < dim + 1:
        raise TooFewAnchorsError(f"{n} anchors: a {dim}D calibration needs at least {dim + 1}")
    if len(pairs) < n * (n - 1) // 2:
        _check_connected(pairs, n)
    if prior is not None:
        prior = np.asarray(prior, dtype=float)
        if prior.shape != (n, dim) or not np.isfinite(prior).all():
            raise InvalidRangeError(f"prior: expected finite ({n}, {dim}) positions, got shape {prior.shape}")

    problem = _Problem(pairs, dist, var, n, dim, loss, f_scale, max_iterations, fit_alpha)
    if prior is None:
        starts = _cold_starts(problem, initializer)
        if not starts:
            raise GeometryError(f"no start: anchors span fewer than {dim} dimensions (collinear or coplanar)")
        refs = _refs_for(starts[0][0], starts[0][1], dim)
        # the first calibration is rare: try every start
        candidates = problem.solve_starts(refs, starts)
        if not candidates:
            raise GeometryError("no start fixes the frame: anchors collinear (coplanar in 3D)")
        if dim == 2 and starts[0][0] == "mds+lift" and not any(c.out.converged for c in candidates):
            # The lifted start crawled back towards the line: the ranges see collinear anchors.
            # The best of those fits is still the answer if the ranges bound the offsets from
            # the line at second order (``degenerate``); otherwise there is no shape to give.
            # (Forced: a crawl can stop where the information is still just invertible.)
            best, _ = problem.select(candidates, None)
            try:
                return _finish(problem, best, refs, None, gauge, len(candidates), ambiguous=True, force_degenerate=True)
            except GeometryError as err:
                raise GeometryError(
                    f"anchors are collinear within the noise: the y axis is undefined ({err})") from None
    else:
        refs = _gauge_refs(prior)
        candidates = [problem.solve(refs, prior, "prior")]
        if not candidates[0].fit_ok or candidates[0].max_z > restart_sigmas:
            # A prior far off (long drift) can sit in the basin of a folded shape (one anchor
            # mirrored across a line through two others). Restart from the ranges alone.
            cold = [("prior+" + name, x) for name, x in _cold_starts(problem, "auto")]
            candidates += problem.solve_starts(refs, cold)
    if prior is not None and prior_std_m is not None:
        std = np.broadcast_to(np.asarray(prior_std_m, dtype=float), (n,))
        if not np.all(np.isfinite(std) & (std > 0)):
            raise SolverArgumentError(f"prior_std_m={prior_std_m!r}: must be finite and > 0 for every anchor")
        problem.prior, problem.prior_weight = prior, dim / std**2
    best, ambiguous = problem.select(candidates, prior)
    sparse = len(pairs) < n * (n - 1) // 2
    if sparse and (prior is None or not best.fit_ok):
        # Missing pairs: every deterministic start can sit in a fold whose cost is 100x the
        # truth's, or the graph may admit a second shape (flip) that fits as well, which only
        # another basin reveals (then ``ambiguous``). More basins: sequential placements that
        # branch over each anchor's mirror choice (``buildup``), and SMACOF from seeded random
        # shapes.
        buildup = _buildup_starts(problem)
        best, ambiguous = problem.add_starts(
            refs, candidates, buildup + _random_smacof_starts(problem, RANDOM_STARTS), prior, best, ambiguous)
        if not buildup and prior is None:
            # No placement order: the random starts are the whole search, and a basin reached
            # from one of them may not be the lowest (noise-free 3D graphs, 12-15 anchors, 1-6
            # dof: 4 of ~2,400 came back ok 4-24 m off, with fits the noise could explain). Draw
            # more until the best shape has been reached from CONFIRM_STARTS starts; a shape
            # not confirmed within MAX_RANDOM_STARTS is reported ambiguous.
            drawn, hits = RANDOM_STARTS, _basin_hits(problem, candidates, best)
            while hits < CONFIRM_STARTS and drawn < MAX_RANDOM_STARTS:
                best, ambiguous = problem.add_starts(
                    refs, candidates, _random_smacof_starts(problem, RANDOM_STARTS, skip=drawn), prior, best, ambiguous)
                drawn, hits = drawn + RANDOM_STARTS, _basin_hits(problem, candidates, best)
            ambiguous = ambiguous or hits < CONFIRM_STARTS
    if prior is None and not sparse and not best.fit_ok and loss == "nlos" and dim == 2 and n <= BUILDUP_ROBUST_MAX_N:
        # NLOS links: every start that embeds all ranges at once is pulled by the long ones, and
        # the robust solve from there keeps that basin. Placements that fit each anchor to its
        # shortest-consistent ranges (several neighbour pairs, one-sided weights) start other
        # basins. 30 % NLOS links, N = 8: rounds at >= 10x the bound 5.6 % -> 4.6 %.
        best, ambiguous = problem.add_starts(refs, candidates, _buildup_starts(problem), prior, best, ambiguous)
    if prior is None and dim == 3 and n > dim + 1:
        # Anchors at similar heights: one anchor mirrored across the plane of the others changes
        # its ranges only to second order, and its mirror can fit within the noise, or better
        # (16 anchors, heights of std 0.5 m over 20 m: 3 of 100 rounds were such mirrors
        # reported ok and unambiguous). The local covariance cannot see a second minimum:
        # solve from each anchor's mirror image; a lower cost wins, a tie is ambiguous.
        best, ambiguous = problem.add_starts(refs, candidates, _plane_mirror_starts(best), prior, best, ambiguous)
    elif prior is not None and dim == 3 and dim + 1 < n <= LATER_MIRROR_PROBE_MAX_N:
        best, ambiguous = _later_mirror_probes(problem, refs, candidates, best, prior, ambiguous)
    if prior is None and dim == 2 and dim + 1 < n <= FLIP_SEARCH_MAX_N and _thin(best.x):
        # Thin layouts (a strip, a corridor): an anchor mirrored across the shape's long axis,
        # or across the line through its two nearest others, changes its ranges only a little,
        # and every start above can end in such a minimum with a fit the noise explains (8
        # anchors on a 40 m x 4 m strip, K = 5: 10 of 3,000 rounds came back 0.03-2.2 in
        # chi-square above the least-squares optimum, 7 of them called unambiguous; 1 after
        # single flips, which needed two anchors flipped at once: up to 8 anchors every pair is
        # flipped too). Solve from each flip, again from a flip that wins: a lower cost wins, a
        # tie is ambiguous.
        # Only flips that converge compete: with dozens of extra starts, one stopped at its
        # iteration cap could otherwise win by a hair over a converged answer (two anchors
        # 1 cm apart: 11 of 1,213 rounds went from ok to not converged).
        for _ in range(2):
            flips = problem.solve_starts(refs, _flip_starts(best.x, pairs_up_to_n=FLIP_PAIRS_MAX_N))
            flips = [c for c in flips if c.out.converged]
            if not flips:
                break
            before = best
            candidates += flips
            best, tie = problem.select(candidates, prior)
            ambiguous = ambiguous or tie
            if best is before:
                break
    tried = len(candidates)
    if not best.fit_ok:
        best, extra = problem.unfold(refs, best)
        tried += extra
    if reject_outliers and not best.fit_ok:
        best = problem.reject_outliers(refs, best)
        best = problem.check_rejected(best)
        if ambiguous and prior is None and not best.keep.all():
            # a tie under the robust loss (different shapes explaining different outliers) is
            # judged again on the pairs the answer kept, where the outliers no longer decide
            ambiguous = problem.ties_on_kept_pairs(refs, best, candidates)
    if prior is None and not ambiguous and (sparse or not best.keep.all()) \
            and not generically_globally_rigid(pairs[best.keep], n, dim):
        # the pairs admit a second shape that fits them as well (e.g. an anchor linked to only
        # dim others, mirrored across them): however well this one fits, it may be the mirror
        ambiguous = True
    return _finish(problem, best, refs, prior, gauge, tried, ambiguous)


def _later_mirror_probes(problem: _Problem, refs, candidates: list, best, prior, ambiguous: bool):
    """A later 3D calibration's answer checked against each anchor's plane mirror: a prior from
    an earlier round of near-coplanar anchors can sit in such a mirror's basin (8 anchors at
    heights within +-0.6 m, a prior with one anchor mirrored: 2 of 480 later rounds came back
    ok and unambiguous with a chi-square more than the tie margin above the shape the ranges
    prefer). Only a mirror the ranges prefer (lower cost, converged: an iteration-capped solve
    must not win by a hair) competes with the answer, as the starts do (``select``: ranges plus
    the prior's term); when the prior keeps the answer, it is flagged ambiguous. A mirror the
    ranges like less never replaces it: the prior comes from the same kind of round and may
    sit in the wrong basin itself (letting such mirrors compete on the prior's term made the
    flagged rounds' answers 0.1-0.2 m worse). ``candidates`` gets the probes (the count of
    starts tried)."""
    probes = [c for c in problem.solve_starts(refs, _plane_mirror_starts(best)) if c.out.converged]
    candidates += probes
    tol = 3.0 * float(np.sqrt(problem.var.max()))
    preferred = [c for c in probes if _cost(c) < _cost(best) and not _same_shape(c.x, best.x, tol)]
    if not preferred:
        return best, ambiguous
    pick, tie = problem.select([best, min(preferred, key=_cost)], prior)
    return pick, ambiguous or tie


def _cost(candidate) -> float:
    return candidate.cost if np.isfinite(candidate.cost) else np.inf


def _check_arguments(gauge, initializer, dim, weighting, f_scale, max_iterations, restart_sigmas, fit_alpha,
                     min_range_std_m, range_std_m):
    if gauge not in GAUGES:
        raise SolverArgumentError(f"gauge={gauge!r}: must be one of {GAUGES}")
    if initializer not in INITIALIZERS:
        raise SolverArgumentError(f"initializer={initializer!r}: must be one of {INITIALIZERS}")
    if dim not in (2, 3):
        raise SolverArgumentError(f"dim={dim!r}: must be 2 or 3")
    if weighting not in WEIGHTINGS:
        raise SolverArgumentError(f"weighting={weighting!r}: must be one of {WEIGHTINGS}")
    if not (isinstance(f_scale, int | float | np.number) and np.isfinite(f_scale) and f_scale > 0):
        raise SolverArgumentError(f"f_scale={f_scale!r}: must be a finite number > 0")
    if not (isinstance(restart_sigmas, int | float | np.number) and restart_sigmas > 0):  # inf: never
        raise SolverArgumentError(f"restart_sigmas={restart_sigmas!r}: must be a number > 0")
    if not (isinstance(max_iterations, int | np.integer) and not isinstance(max_iterations, bool)
            and max_iterations >= 1):
        raise SolverArgumentError(f"max_iterations={max_iterations!r}: must be an integer >= 1")
    if not (isinstance(fit_alpha, int | float | np.number) and 0 < fit_alpha < 1):
        raise SolverArgumentError(f"fit_alpha={fit_alpha!r}: must be in (0, 1)")
    if weighting == "sample" and not (np.isfinite(min_range_std_m) and min_range_std_m > 0):
        raise SolverArgumentError(f"min_range_std_m={min_range_std_m!r}: must be a finite number > 0")
    if range_std_m is not None and not (isinstance(range_std_m, int | float | np.number)
                                        and np.isfinite(range_std_m) and range_std_m > 0):
        raise SolverArgumentError(f"range_std_m={range_std_m!r}: must be a finite number > 0")


@dataclass
class _Candidate:
    """One solve in the internal gauge, with its fit verdict."""

    x: np.ndarray
    out: object  # PairSolution
    keep: np.ndarray  # (P,) bool: pairs used
    name: str
    chi2: float
    dof: int
    p_value: float
    fit_ok: bool
    max_z: float
    prior_score: float | None = None  # memo of _Problem.score once the prior is known

    @property
    def cost(self) -> float:
        return self.out.cost


class _Problem:
    """The data of one calibration and the solves on it (several starts share it)."""

    def __init__(self, pairs, dist, var, n, dim, loss, f_scale, max_iterations, fit_alpha):
        self.pairs, self.dist, self.var, self.n, self.dim = pairs, dist, var, n, dim
        self.inv_var = 1.0 / var
        self.loss, self.f_scale, self.max_iterations, self.fit_alpha = loss, f_scale, max_iterations, fit_alpha
        self._full = None
        self.prior = self.prior_weight = None  # set when the prior's uncertainty is known

    def score(self, cand: _Candidate) -> float:
        """What the starts compete on: the cost, plus the prior's chi-square when it is known."""
        if self.prior is None:
            return _cost(cand)
        if cand.prior_score is None:  # unfold compares its best against every reflection
            rot, trans = rigid_align(cand.x, self.prior, allow_reflection=True)
            d2 = ((cand.x @ rot.T + trans - self.prior) ** 2).sum(1)
            cand.prior_score = _cost(cand) + 0.5 * float(d2 @ self.prior_weight)
        return cand.prior_score

    @property
    def full(self) -> np.ndarray:
        if self._full is None:
            self._full = _full_matrix(self.pairs, self.dist, self.n)
        return self._full

    def solve(self, refs, start, name, keep=None) -> _Candidate:
        n, dim = self.n, self.dim
        if keep is None:
            keep = np.ones(len(self.pairs), dtype=bool)
            pairs, dist, inv_var = self.pairs, self.dist, self.inv_var
        else:
            pairs, dist, inv_var = self.pairs[keep], self.dist[keep], self.inv_var[keep]
        rot0, trans0 = paper_frame(start, refs) if not _in_gauge(start, refs) else (None, None)
        x0 = start if rot0 is None else start @ rot0.T + trans0
        structure = _structure(pairs, n, dim, refs) if keep.all() else pair_structure(
            pairs, n, dim, _free_mask(n, dim, refs))
        if self.loss != "linear" and not name.startswith("buildup"):
            # Robust losses are non-convex: start them from the plain least-squares solution so
            # an outlier-corrupted start does not trap them in a wrong minimum. (Not the build-up
            # placements: they fit each anchor on its own ranges already, and the plain solve
            # would pull them all back into the outliers' basin. The re-solves that refine a
            # build-up winner, its unfold and pair rejection, carry the name and skip it too:
            # 14 -> 12 rounds at 10x of 250 NLOS rounds against pre-solving them.)
            x0 = solve_pair_ranges(structure, x0, dist, inv_var, "linear", 1.0, self.max_iterations).positions
        # Reweighting converges only linearly (slowly when many residuals sit near the loss's
        # knee): the robust stage gets four times the plain stage's iteration budget.
        budget = self.max_iterations if self.loss == "linear" else 4 * self.max_iterations
        out = solve_pair_ranges(structure, x0, dist, inv_var, self.loss, self.f_scale, budget)
        z = out.residuals * np.sqrt(inv_var)
        chi2 = float(z @ z) if np.all(np.isfinite(z)) else np.inf
        dof = len(dist) - structure.n_free
        p_value = float(chdtrc(dof, chi2)) if dof > 0 else 1.0
        fit_ok = bool(out.converged and (dof <= 0 or p_value >= self.fit_alpha))
        return _Candidate(out.positions, out, keep, name, chi2, dof, p_value, fit_ok, float(np.abs(z).max()))

    def solve_starts(self, refs, starts) -> list[_Candidate]:
        out = []
        for name, start in starts:
            try:
                out.append(self.solve(refs, start, name))
            except GeometryError:  # this start cannot be put in the gauge (degenerate): skip it
                continue
        return out

    def select(self, candidates: list[_Candidate], prior) -> tuple[_Candidate, bool]:
        """The lowest cost, unless the ranges cannot tell it from another shape: candidates whose
        cost (twice it: the chi-square under the plain loss, its robust counterpart otherwise)
        lies within the fit test's one-dof margin of the lowest are indistinguishable (e.g. the
        two folds of a quadrilateral with a missing diagonal). Then the prior decides (the
        closest after rigid alignment); without a prior the result is flagged ambiguous. The
        quantity compared is the one minimized: under a robust loss the plain chi-square is
        dominated by the outliers, and a shape that fits them better would pass for a tie."""
        best = min(candidates, key=_cost)
        if len(candidates) == 1 or not np.isfinite(best.chi2):
            return best, False
        if self.prior is not None:
            pick = min(candidates, key=self.score)
            tol = 3.0 * float(np.sqrt(self.var.max()))
            # ambiguous: the ranges alone preferred another shape and the prior overruled them
            return pick, bool(best.chi2 < pick.chi2 and not _same_shape(pick.x, best.x, tol))
        margin = float(chdtri(1, self.fit_alpha))
        tol = 3.0 * float(np.sqrt(self.var.max()))  # shapes closer than this are the same shape
        near = [c for c in candidates if c.out.converged and 2.0 * (_cost(c) - _cost(best)) <= margin
                and not _same_shape(c.x, best.x, tol)]
        if not near:
            return best, False
        if prior is None:
            return best, True
        pick = min([best, *near], key=lambda c: _shape_distance(c.x, prior))
        others = [c for c in [best, *near] if not _same_shape(c.x, pick.x, tol)]
        # the prior decides only if it is clearly closer to one shape than to the others
        ambiguous = any(_shape_distance(c.x, prior) < 2.0 * _shape_distance(pick.x, prior) for c in others)
        return pick, ambiguous

    def add_starts(self, refs, candidates: list[_Candidate], starts, prior, best, ambiguous):
        """Solve ``starts``, add them to ``candidates`` (in place) and select again; the current
        (best, ambiguous) when none could be solved."""
        more = self.solve_starts(refs, starts)
        if not more:
            return best, ambiguous
        candidates += more
        return self.select(candidates, prior)

    def ties_on_kept_pairs(self, refs, best: _Candidate, candidates: list[_Candidate]) -> bool:
        """Whether another candidate's shape, re-solved on the pairs ``best`` kept, fits them
        within the fit test's one-dof chi-square margin of ``best`` (then the kept ranges cannot
        tell the two shapes apart)."""
        margin = float(chdtri(1, self.fit_alpha))
        tol = 3.0 * float(np.sqrt(self.var.max()))
        tried: list[np.ndarray] = []
        for c in sorted(candidates, key=_cost):
            if not c.out.converged or _same_shape(c.x, best.x, tol) or any(_same_shape(c.x, t, tol) for t in tried):
                continue
            tried.append(c.x)
            alt = self.solve(refs, c.x, c.name, best.keep)
            if alt.out.converged and alt.chi2 - best.chi2 <= margin and not _same_shape(alt.x, best.x, tol):
                return True
        return False

    def unfold(self, refs, best: _Candidate) -> tuple[_Candidate, int]:
        """Single-anchor reflections of a poorly fitting solution: a fold mirrors an anchor (or a
        few) across a line (plane) through others; reflecting it back is one start away."""
        tried = 0
        misfit = self._anchor_misfit(best)
        worst = np.argsort(-misfit)[: min(self.n, 16)]
        if best.dof > 0 and np.isfinite(best.chi2):
            # Reflecting an anchor back removes (to first order) at most the misfit of its own
            # pairs; if the worst anchors' misfits together cannot bring the chi-square under
            # the fit threshold, the misfit is spread over the shape (a wrong model, e.g. robots
            # that moved through a long round), not a fold: skip the solves (18 of 0.4 s each
            # for a 3D 64-anchor round).
            if 2.0 * float(misfit[worst].sum()) < best.chi2 - float(chdtri(best.dof, self.fit_alpha)):
                return best, tried
        for _ in range(2):  # passes: a second fold can hide behind the first
            improved = False
            for k in np.argsort(-self._anchor_misfit(best))[: min(self.n, 16)]:
                start = _reflect_anchor(best.x, int(k))
                if start is None:
                    continue
                try:
                    cand = self.solve(refs, start, best.name + "+unfold", best.keep)
                except GeometryError:  # the mirrored shape is collinear (cannot be put in the gauge): skip it
                    continue
                tried += 1
                if self.score(cand) < self.score(best) - 1e-9:
                    best, improved = cand, True
                    if best.fit_ok:
                        return best, tried
            if not improved:
                break
        return best, tried

    def _anchor_misfit(self, cand: _Candidate) -> np.ndarray:
        z2 = np.zeros(len(self.pairs))
        z2[cand.keep] = cand.out.residuals ** 2 * self.inv_var[cand.keep]
        return np.bincount(self.pairs[:, 0], z2, self.n) + np.bincount(self.pairs[:, 1], z2, self.n)

    def check_rejected(self, best: _Candidate, sigmas: float = 4.0, alpha_after: float = 0.05) -> _Candidate:
        """Two checks on a fit reached by dropping pairs, each reporting a poor fit, not ok:

        - the pairs were chosen *because* they fit worst, so the remaining chi-square is biased
          low: the fit test is repeated at the stricter level ``alpha_after``;
        - NLOS only ever lengthens a range: every dropped pair must measure *longer* than the
          accepted shape says. One measured shorter by more than ``sigmas`` standard deviations
          contradicts the shape (a good pair was dropped to fit a biased one).

        30 % NLOS links, N = 8: rounds at 10x the bound or worse reported ok 5 % -> see the
        localization benchmark (``robust_nlos30_wrong_converged_rate_n8``)."""
        if not best.fit_ok or best.keep.all():
            return best
        if best.dof > 0 and best.p_value < alpha_after:
            return replace(best, fit_ok=False)
        dropped = ~best.keep
        i, j = self.pairs[dropped, 0], self.pairs[dropped, 1]
        model = np.linalg.norm(best.x[i] - best.x[j], axis=1)
        z = (model - self.dist[dropped]) * np.sqrt(self.inv_var[dropped])  # > 0: measured too short
        if z.max() <= sigmas:
            return best
        return replace(best, fit_ok=False)

    def _rejection_can_fit(self, best: _Candidate, max_drops: int) -> bool:
        """Whether dropping at most ``max_drops`` too-long pairs could pass the fit test at all.

        Dropping pair p lowers the chi-square by z_p^2 / (1 - h_p) to first order (h_p: its
        leverage, the whitened Jacobian row's quadratic form in the covariance; under a robust
        loss a pair with a large residual already carries almost no weight, and the gain is
        about z_p^2). If even the largest such gains cannot bring the chi-square under the
        test's threshold, the misfit is spread over the shape (a wrong model, e.g. robots that moved
        through a long round), not carried by a few outliers: the greedy drops would only burn
        one solve each (a 3D 64-anchor first calibration: 40 s) and end in the same poor fit.
        """
        if best.dof - max_drops < 1 or not np.isfinite(best.chi2):
            return True  # small problems: the loop's own checks decide
        try:
            cov = best.out.covariance()
        except GeometryError:
            return True
        keep = best.keep
        pairs = self.pairs[keep]
        i, j = pairs[:, 0], pairs[:, 1]
        n, dim = self.n, self.dim
        sw = np.sqrt(self.inv_var[keep])
        z = best.out.residuals * sw
        diff = best.x[i] - best.x[j]
        # rows whitened with the weights the solve used (robust weights included): the
        # covariance is the inverse of that information, so 0 <= h_p <= 1
        u = diff / np.maximum(np.linalg.norm(diff, axis=1), 1e-12)[:, None] * np.sqrt(best.out.weights)[:, None]
        c = cov.reshape(n, dim, n, dim)
        block = c[i, :, i, :] + c[j, :, j, :] - c[i, :, j, :] - c[j, :, i, :]  # (P, dim, dim)
        h = np.einsum("pa,pab,pb->p", u, block, u)
        gain = z**2 / np.maximum(1.0 - h, 1e-3)
        gain = np.sort(gain[z < 0])[::-1][:max_drops]  # only too-long pairs are dropped
        if not len(gain):
            return False
        # after k drops the test's threshold is lower by about one per dof: any k may pass
        k = np.arange(1, len(gain) + 1)
        threshold = chdtri(best.dof - k, self.fit_alpha)
        return bool(np.any(np.cumsum(gain) >= best.chi2 - threshold))

    def reject_outliers(self, refs, best: _Candidate, tries: int = 1, max_fraction: float = 0.4) -> _Candidate:
        """Drop one pair at a time while the fit fails and the shape stays rigid.

        Each step re-solves without each of the ``tries`` pairs that are longest for the shape
        (default 1: the longest) and drops the one whose removal fits best (lowest chi-square).
        Only too-long pairs are suspects: NLOS only ever lengthens a range, and with many biased links the solution is
        pulled towards them, so the largest residual either way often sits on a good pair that
        the biased ones made look short (30 % NLOS links, N = 8: median error 4.4 -> 1.9x the
        clean bound, rounds at 10x 32 % -> 11 %).

        A pair is only identifiable as the outlier while the others keep some redundancy: with
        fewer than two degrees of freedom left, dropping *any* pair fits perfectly, so nothing
        is dropped and the poor fit is reported instead; likewise when no fit is reached within
        ``max_fraction`` of the pairs dropped.
        """
        start = best
        # One solve per dropped pair: at N = 64 (2,016 pairs) 40 % would be 806 solves, minutes
        # for one round. Beyond 2N drops (48 at least) the model is wrong (e.g. robots that
        # moved through a long round), not a few outliers: stop and report the poor fit.
        max_drops = min(int(max_fraction * len(self.pairs)), max(48, 2 * self.n))
        if not self._rejection_can_fit(best, max_drops):
            return start
        for _ in range(max_drops):
            if best.fit_ok or best.dof - 1 < 2:
                break
            z = np.zeros(len(self.pairs))
            z[best.keep] = best.out.residuals * np.sqrt(self.inv_var[best.keep])
            live = np.flatnonzero(best.keep)
            too_long = live[np.argsort(z[live])][: tries]  # residual = model - measured < 0
            trial = None
            for worst in too_long.tolist():
                keep = best.keep.copy()
                keep[worst] = False
                if not _connected(self.pairs[keep], self.n):
                    continue
                try:
                    cand = self.solve(refs, best.x, best.name, keep)
                    cand.out.covariance()  # rigid: the remaining pairs still fix every coordinate
                except GeometryError:
                    continue
                if trial is None or cand.chi2 < trial.chi2:
                    trial = cand
            if trial is None:
                break
            best = trial
        # More than ``max_fraction`` of the pairs "outliers" is a wrong model (e.g. robots that
        # moved during a long round), not outliers: keep every pair and report the poor fit.
        return best if best.fit_ok else start


def _shape_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Largest anchor distance between two shapes after the best rigid alignment (mirror allowed)."""
    rot, trans = rigid_align(a, b, allow_reflection=True)
    return float(np.sqrt(((a @ rot.T + trans - b) ** 2).sum(1)).max())


def _same_shape(a: np.ndarray, b: np.ndarray, tol: float) -> bool:
    """Every anchor within ``tol`` after some rigid motion (mirror allowed). Two starts that ended
    in the same minimum share the internal gauge, so the identity or the gauge's mirror usually
    shows it without the SVD of :func:`_shape_distance` (a third of a small first calibration)."""
    d = a - b
    if float((d * d).sum(1).max()) <= tol * tol:
        return True
    m = a.copy()
    m[:, -1] = -m[:, -1]
    d = m - b
    if float((d * d).sum(1).max()) <= tol * tol:
        return True
    return _shape_distance(a, b) <= tol


def _reflection_uncertain(positions: np.ndarray, covariance: np.ndarray, dim: int, sigmas: float = 3.0) -> bool:
    """The paper frame's reflection rule (the anchors' last coordinates sum positive) within
    ``sigmas`` standard deviations of flipping. Ranges cannot see a reflection: near the rule's
    threshold the noise decides on which side of the x axis (xy plane) the team lands."""
    n = len(positions)
    axis = dim - 1
    total = float(positions[:, axis].sum())
    idx = np.arange(n) * dim + axis
    var = float(covariance[np.ix_(idx, idx)].sum())
    return bool(abs(total) < sigmas * math.sqrt(max(var, 0.0)))


def _finish(problem: _Problem, best: _Candidate, refs, prior, gauge, tried, ambiguous=False,
            force_degenerate=False) -> CalibrationResult:
    """The result of ``best``; ``force_degenerate``: treat it as fixed only to second order along its
    least-determined direction even if the information is (just) invertible."""
    n, dim = problem.n, problem.dim
    out, x_gauge = best.out, best.x
    cov_gauge = None if force_degenerate else _covariance_or_none(out)
    linearized = cov_gauge
    if cov_gauge is not None and prior is None and shape_beyond_scene(
            best.x, problem.pairs[best.keep], problem.dist[best.keep], problem.inv_var[best.keep]):
        # Invertible, but the *shape* (not just the frame: anchors 0 and 1 close make the paper
        # frame's rotation, not the shape, uncertain) has a direction whose linearized variance
        # exceeds the scene's size: an anchor a few cm from another, in line with a third, came
        # back "ok" with a 160 m std. The ranges fix it only to second order there.
        cov_gauge = None
    degenerate = 0  # null directions
    if cov_gauge is None:
        # Collinear within the noise (three anchors whose ranges do not close a triangle): the
        # least-squares optimum is on the line and the information has a null direction. That
        # is still the best fit, and the ranges bound the offset at second order: report it as
        # ``degenerate`` with the profile likelihood's width there (raises if it is unbounded).
        s, keep = out.structure, best.keep
        if not generically_rigid(problem.pairs[keep], n, dim):
            # a flexible graph (an anchor hanging off one other, a four-bar linkage): its exact
            # fits form a continuum, bounded or not; no shape to report
            raise GeometryError("degenerate anchor geometry: the measured pairs do not make a rigid shape "
                                "(collinear / coplanar anchors, or too few pairs for a rigid shape)")
        # One null direction only: with two or more (four anchors on a line) the null space's
        # basis is arbitrary and one-sigma points along it were 2-30x too narrow (review).
        try:
            x_gauge, cov_gauge, degenerate = degenerate_fit(
                x_gauge, s.column < s.n_free, out.information[:s.n_free, :s.n_free], problem.pairs[keep],
                problem.dist[keep], out.weights, max_null=1)
        except GeometryError:
            if linearized is None:
                raise
            cov_gauge = linearized  # no better account than the linearized one: report that
    if degenerate:
        keep = best.keep
        pairs = problem.pairs[keep]
        residuals = np.linalg.norm(x_gauge[pairs[:, 0]] - x_gauge[pairs[:, 1]], axis=1) - problem.dist[keep]
        z = residuals * np.sqrt(problem.inv_var[keep])
        out = replace(out, positions=x_gauge, residuals=residuals, cost=robust_cost(z, problem.loss, problem.f_scale))
        best = replace(best, x=x_gauge, out=out, chi2=float(z @ z), max_z=float(np.abs(z).max()))
    if prior is None:
        # Re-apply the frame's sign rules to the solution (only axis flips here): the cost is
        # mirror-invariant, so the optimizer may have crossed to the other side.
        signs = _gauge_flip(x_gauge, refs)
        if signs is None:
            positions, covariance = x_gauge, cov_gauge
        else:
            positions = x_gauge * signs
            flips = np.tile(signs, n)
            covariance = cov_gauge * flips[:, None] * flips[None, :]  # exact +-1: no leakage
        ambiguous = ambiguous or _reflection_uncertain(positions, covariance, dim)
    else:
        pivot = 0 if gauge == "anchor0" else None
        rot, trans = rigid_align(x_gauge, prior, allow_reflection=True, pivot=pivot)
        positions = x_gauge @ rot.T + trans
        covariance = _rotate_covariance(cov_gauge, rot, n, dim)
    residuals = np.full(len(problem.pairs), np.nan)
    residuals[best.keep] = out.residuals
    keep = best.keep
    if degenerate:
        status = "degenerate"
    elif out.converged and best.fit_ok:
        status = "ok"
    else:
        status = "poor_fit" if out.converged else "not_converged"
    return CalibrationResult(
        positions=positions,
        covariance=covariance,
        pairs=problem.pairs[keep] if not keep.all() else problem.pairs,
        ranges_m=problem.dist[keep] if not keep.all() else problem.dist,
        residuals_m=out.residuals,
        range_var_m2=problem.var[keep] if not keep.all() else problem.var,
        iterations=out.iterations,
        cost=out.cost,
        converged=status == "ok",
        message=_status_message(status, out.message, best, degenerate),
        initializer=best.name,
        gauge_refs=refs,
        chi2=best.chi2,
        dof=best.dof,
        fit_p_value=best.p_value,
        status=status,
        optimizer_converged=bool(out.converged),
        rejected_pairs=problem.pairs[~keep],
        starts_tried=tried,
        ambiguous=ambiguous,
    )


def _covariance_or_none(out) -> np.ndarray | None:
    try:
        return out.covariance()
    except GeometryError:
        return None


def _status_message(status: str, optimizer_message: str, best: _Candidate, null_directions: int) -> str:
    if status == "poor_fit":
        return f"converged to a poor fit: chi2 {best.chi2:.1f} on {best.dof} dof (p = {best.p_value:.2g})"
    if status == "degenerate":
        return (f"degenerate geometry: {null_directions} direction(s) of the shape fixed by the ranges only to "
                f"second order (anchors collinear within the noise); the covariance there is the profile "
                f"chi-square's one-sigma half-width")
    return optimizer_message


def _refs_for(name: str, start: np.ndarray, dim: int) -> tuple[int, ...]:
    if dim == 2 and name == "trilateration":
        # Trilateration already places anchor 0 at the origin and anchor 1 on +x: that is
        # the internal gauge, up to the mirror image the final sign rule settles.
        return (0, 1)
    return frame_refs(start)


def _in_gauge(x: np.ndarray, refs: tuple[int, ...]) -> bool:
    """True when x already has refs[0] at the origin and refs[1] on the +x axis (2D)."""
    if len(refs) != 2:
        return False
    o, a = x[refs[0]], x[refs[1]]
    return bool(o[0] == 0.0 and o[1] == 0.0 and a[1] == 0.0 and a[0] > 0.0)


def _reflect_anchor(x: np.ndarray, k: int) -> np.ndarray | None:
    """x with anchor k mirrored across the line (2D) or plane (3D) through its nearest others."""
    n, dim = x.shape
    if n <= dim + 1:
        return None
    d = np.linalg.norm(x - x[k], axis=1)
    d[k] = np.inf
    near = np.argsort(d)[:dim]
    base = x[near[0]]
    if dim == 2:
        t = x[near[1]] - base
        norm = np.linalg.norm(t)
        if norm < 1e-9:
            return None
        normal = np.array([-t[1], t[0]]) / norm
    else:
        normal = np.cross(x[near[1]] - base, x[near[2]] - base) if len(near) > 2 else None
        if normal is None or np.linalg.norm(normal) < 1e-9:
            return None
        normal = normal / np.linalg.norm(normal)
    out = x.copy()
    out[k] = x[k] - 2.0 * ((x[k] - base) @ normal) * normal
    return out


# A 2D shape whose second principal variance is below this fraction of the first is thin (the
# batched first calibration's ``min_aspect``: it hands such teams to this solver).
THIN_ASPECT = 0.1
# The single flips cost up to 4N solves (a thin first calibration: 2.6 ms at N = 8, 8 ms at 16,
# 52 ms at 32, 0.55 s at 64); the starts alone missed no least-squares optimum on thin strips
# of 16 and 32 anchors (0 of 1,000 rounds each in bench_localization), 3 of 500 at 8.
FLIP_SEARCH_MAX_N = 16
# ... and flips of every two anchors across the axis (n (n - 1) / 2 more solves; 6-8 ms in all
# at N = 8, ~30 ms with a robust loss) up to this many
FLIP_PAIRS_MAX_N = 8
# Later 3D calibrations probe single-anchor plane mirrors up to this team size (one solve per
# anchor whose mirror lies beyond its std: a later calibration of 8 anchors 1.5 -> 3.0 ms, of
# 16 anchors 11 -> 16 ms; at 64 a later round would pay up to 64 solves of ~15 ms, where the
# first calibration, run once, still probes every anchor).
LATER_MIRROR_PROBE_MAX_N = 16


def _thin(x: np.ndarray) -> bool:
    s = np.linalg.svd(x - x.mean(0), compute_uv=False)
    return bool(s[1] ** 2 < THIN_ASPECT * s[0] ** 2)


def _flip_starts(x: np.ndarray, pairs_up_to_n: int = 0) -> list[tuple[str, np.ndarray]]:
    """``x`` with one anchor mirrored, for every anchor: across the line through its two nearest
    others (``_reflect_anchor``) and across the shape's principal axis (2D); with at most
    ``pairs_up_to_n`` anchors also every two anchors mirrored across the axis together."""
    n = len(x)
    centre = x.mean(0)
    axis = np.linalg.svd(x - centre)[2][0]
    normal = np.array([-axis[1], axis[0]])
    mirrored = x - 2.0 * ((x - centre) @ normal)[:, None] * normal
    starts = []
    for k in range(n):
        near = _reflect_anchor(x, k)
        if near is not None:
            starts.append(("flip-near", near))
        across = x.copy()
        across[k] = mirrored[k]
        starts.append(("flip-axis", across))
    if n <= pairs_up_to_n:
        for k in range(n):
            for j in range(k + 1, n):
                both = x.copy()
                both[[k, j]] = mirrored[[k, j]]
                starts.append(("flip-axis-pair", both))
    return starts


def _plane_mirror_starts(best, sigmas: float = 1.0) -> list[tuple[str, np.ndarray]]:
    """``best``'s shape with one anchor k mirrored across the best-fit plane of the others (3D
    first calibrations; later ones up to ``LATER_MIRROR_PROBE_MAX_N`` anchors), for every k
    whose mirror image lies more than ``sigmas`` of its own std along the plane's normal away:
    a nearer image is the same answer within the covariance and its solve (~15 ms at N = 64)
    would be spent for nothing. At 2 sigma the screen let one of the three seeds of
    ``test_a_3d_anchor_mirrored_across_the_others_plane_...`` through."""
    x = best.x
    n, dim = x.shape
    try:
        cov = best.out.covariance()
    except GeometryError:
        return []
    starts = []
    for k in range(n):
        others = np.delete(x, k, axis=0)
        centre = others.mean(axis=0)
        normal = np.linalg.svd(others - centre, full_matrices=False)[2][-1]
        offset = float((x[k] - centre) @ normal)
        block = cov[k * dim:(k + 1) * dim, k * dim:(k + 1) * dim]
        if 2.0 * abs(offset) <= sigmas * math.sqrt(max(float(normal @ block @ normal), 0.0)):
            continue
        mirrored = x.copy()
        mirrored[k] = x[k] - 2.0 * offset * normal
        starts.append((best.name + "+mirror", mirrored))
    return starts


def _connected(pairs: np.ndarray, n: int) -> bool:
    try:
        _check_connected(pairs, n)
    except DisconnectedGraphError:
        return False
    return True


def _full_matrix(pairs, dist, n) -> np.ndarray:
    full = np.full((n, n), np.nan)
    full[pairs[:, 0], pairs[:, 1]] = dist
    full[pairs[:, 1], pairs[:, 0]] = dist
    full.flat[:: n + 1] = 0.0
    return full


def _cold_starts(problem: _Problem, initializer: str) -> list[tuple[str, np.ndarray]]:
    """Starts from the ranges alone, the requested one first: trilateration (the paper's), classical
    MDS on the shortest-path-completed matrix, and SMACOF on the measured pairs only (missing
    pairs get weight 0, so the shortest-path fill cannot fold the start)."""
    full, dim = problem.full, problem.dim
    starts = []
    order = ["trilateration", "mds"] if initializer != "mds" else ["mds", "trilateration"]
    for name in order:
        try:
            if name == "trilateration":
                starts.append((name, trilaterate_initial(full, dim)))
            else:
                mds = classical_mds(full, dim)
                starts.append(("mds", mds))
                if np.isnan(full).any():
                    starts.append(("smacof", smacof(full, mds, problem.inv_var, problem.pairs)))
        except GeometryError:
            if name == initializer:
                raise
    if not starts:
        # Anchors on robots of similar height (3D), or spread along a corridor (2D): noise can
        # leave the ranges no embedding in the full dimension, and both starts come out flat. A
        # flat start is a saddle of the cost (zero gradient off the line / plane), so lift it
        # along MDS's next axis and let least squares find the offsets (or report the geometry
        # degenerate if the ranges cannot).
        starts.append(("mds+lift", _lifted_mds(full, dim)))
    return starts


RANDOM_STARTS = 12
# Graphs without a placement order: starts that must reach the best shape, and the most drawn.
CONFIRM_STARTS = 3
MAX_RANDOM_STARTS = 240
# Robust build-up placements try every pair of neighbours per anchor: ~45 ms at N = 8, ~1.2 s at
# N = 64. Measured to help at N = 8 (30 % NLOS: 5.6 -> 4.6 % of rounds at 10x); at N = 16 the
# plain starts already leave none at 10x.
BUILDUP_ROBUST_MAX_N = 12


def _buildup_starts(problem: _Problem) -> list[tuple[str, np.ndarray]]:
    """Sequential placements branching over each anchor's mirror choice (``buildup``); under
    the ``nlos`` loss each placement down-weights ranges measured longer than it (NLOS)."""
    n = problem.n
    robust_c = problem.f_scale if problem.loss == "nlos" else None
    weight = np.nan_to_num(_full_matrix(problem.pairs, problem.inv_var, n))  # 0 where missing
    tol = 3.0 * float(np.sqrt(problem.var.max()))
    return [("buildup", x) for x in buildup_starts(problem.full, weight, problem.dim, tol, robust_c=robust_c)]


def _random_smacof_starts(problem: _Problem, count: int, skip: int = 0) -> list[tuple[str, np.ndarray]]:
    """SMACOF (measured pairs only) from ``count`` random shapes of the ranges' extent, seeded
    so the result is reproducible; ``skip``: the shapes of the sequence already used."""
    rng = np.random.default_rng(0)
    rng.standard_normal((skip, problem.n, problem.dim))
    positive = problem.full[np.isfinite(problem.full) & (problem.full > 0)]
    scale = float(np.median(positive)) if positive.size else 1.0  # all ranges zero: any unit
    return [("smacof-random", smacof(problem.full, scale * rng.standard_normal((problem.n, problem.dim)),
                                     problem.inv_var, problem.pairs)) for _ in range(count)]


def _basin_hits(problem: _Problem, candidates: list[_Candidate], best: _Candidate) -> int:
    """How many converged random-start candidates (``smacof-random``, ``best`` included if it is
    one) ended in ``best``'s shape (``_same_shape``'s tolerance): the deterministic starts often
    share a basin with each other and are not independent evidence."""
    tol = 3.0 * float(np.sqrt(problem.var.max()))
    return sum(bool(c.name == "smacof-random" and c.out.converged and _same_shape(c.x, best.x, tol))
               for c in candidates)


def _lifted_mds(full: np.ndarray, dim: int = 3) -> np.ndarray:
    filled = _shortest_path_filled(full)
    n = filled.shape[0]
    centering = np.eye(n) - 1.0 / n
    vals, vecs = np.linalg.eigh(-0.5 * centering @ (filled**2) @ centering)
    # the constant vector is in the centred Gram's null space: with a negative last eigenvalue it
    # would outrank the real last axis and lift nothing
    real_axes = np.abs(vecs.sum(0)) < 0.5 * np.sqrt(n)
    order = [k for k in np.argsort(vals)[::-1] if real_axes[k]][:dim]
    if len(order) < dim or not np.all(np.isfinite(filled)):
        # e.g. 4 anchors in 3D with most pairs dropped: no dim axes to lift along
        raise GeometryError(f"the ranges give fewer than {dim} axes to start from: too few pairs for a {dim}D shape")
    scale = np.sqrt(np.maximum(vals[order], 0.0))
    for axis in range(1, dim):  # a definite lift: 5 % of the largest extent
        scale[axis] = max(scale[axis], 0.05 * scale[0])
    return vecs[:, order] * scale


def _shortest_path_filled(full: np.ndarray) -> np.ndarray:
    if not np.isnan(full).any():
        return full
    # csgraph reads a dense entry below ~1e-8 as "no edge": a measured zero range (coincident
    # anchors) stays an edge of 1 um (the fill only seeds a start)
    graph = np.where(np.isnan(full), 0.0, np.maximum(full, 1e-6))
    np.fill_diagonal(graph, 0.0)
    return shortest_path(graph, method="D", directed=False)


def smacof(full: np.ndarray, x0: np.ndarray, inv_var: np.ndarray, pairs: np.ndarray,
           iterations: int = 100, tol: float = 1e-6) -> np.ndarray:
    """Weighted SMACOF (stress majorization) over the measured pairs only (weights 1/sigma^2).

    Each Guttman transform lowers the weighted stress monotonically; it is far less prone than
    Gauss-Newton to cross into a folded shape from a rough start, which makes it a good start.
    """
    n = len(x0)
    w = np.zeros((n, n))
    w[pairs[:, 0], pairs[:, 1]] = inv_var
    w[pairs[:, 1], pairs[:, 0]] = inv_var
    delta = np.nan_to_num(full)
    v = -w.copy()
    v.flat[:: n + 1] = w.sum(1)
    v_pinv = np.linalg.pinv(v)
    x = x0.copy()
    prev = np.inf
    for _ in range(iterations):
        d = np.linalg.norm(x[:, None] - x[None], axis=-1)
        ratio = np.where(d > 1e-12, w * delta / np.maximum(d, 1e-12), 0.0)
        b = -ratio
        b.flat[:: n + 1] = ratio.sum(1)
        x = v_pinv @ (b @ x)
        stress = float((w * (np.linalg.norm(x[:, None] - x[None], axis=-1) - delta) ** 2).sum())
        if prev - stress <= tol * max(prev, 1e-300):
            break
        prev = stress
    return x


def _gauge_flip(x_gauge: np.ndarray, refs: tuple[int, ...]) -> np.ndarray | None:
    """(dim,) axis signs that put a gauge-frame solution in the paper frame, None if none flip.

    The gauge anchors are where ``paper_frame`` puts them (origin, +-x axis, xy-plane), so its
    rotation is diagonal. Degenerate shapes never get here: their information matrix is
    singular, which ``PairSolution.covariance`` reports.
    """
    if x_gauge.shape[1] == 3:
        signs = np.diag(paper_frame(x_gauge, refs)[0]).copy()
        return None if signs.min() > 0 else signs
    origin = x_gauge[refs[0]]
    sx = 1.0 if x_gauge[refs[1], 0] >= origin[0] else -1.0
    sy = 1.0 if float(x_gauge[:, 1].sum()) >= len(x_gauge) * origin[1] else -1.0
    return None if sx > 0 and sy > 0 else np.array([sx, sy])


def _rotate_covariance(cov: np.ndarray, rot: np.ndarray, n: int, dim: int) -> np.ndarray:
    """Covariance of x @ rot.T per anchor: (I_n kron R) cov (I_n kron R)^T."""
    left = np.matmul(rot, cov.reshape(n, dim, n * dim)).reshape(n * dim, n, dim)
    return np.matmul(left, rot.T).reshape(n * dim, n * dim)


# -- input handling ----------------------------------------------------------------------------
def _pair_data(ranges, range_std_m, min_range_std_m):
    if isinstance(ranges, RangeMatrix):
        matrix = ranges
        complete = matrix.complete_symmetric(min_range_std_m, range_std_m)
        if complete is not None:  # the usual round: nothing to validate further
            return (*complete, matrix.n_anchors)
        mean, count = matrix.mean_m, matrix.count
        bad = (count > 0) & ~np.isfinite(mean)  # the arrays may have changed since construction
        if bad.any():
            i, j = np.argwhere(bad)[0]
            raise InvalidRangeError(f"range ({i}, {j}) = {mean[i, j]!r} with count {count[i, j]}: not finite")
    else:
        try:
            mean = np.asarray(ranges, dtype=float)
        except (TypeError, ValueError) as err:
            raise InvalidRangeError(f"ranges: not a numeric matrix ({err})") from None
        if mean.ndim != 2 or mean.shape[0] != mean.shape[1]:
            raise InvalidRangeError(f"ranges: expected a square (n, n) matrix, got shape {mean.shape}")
        if np.isinf(mean).any():
            i, j = np.argwhere(np.isinf(mean))[0]
            raise InvalidRangeError(f"range ({i}, {j}) = {mean[i, j]!r}: not finite")
        # One range per unordered pair: the two directions (if both given) are averaged.
        both = np.stack([mean, mean.T])
        given = np.isfinite(both)
        n_given = given.sum(0)
        sym = np.where(n_given > 0, np.where(given, both, 0.0).sum(0) / np.maximum(n_given, 1), np.nan)
        upper = np.triu(np.isfinite(sym), 1)
        std = np.full(mean.shape, range_std_m if range_std_m is not None else min_range_std_m)
        matrix = RangeMatrix(np.where(upper, sym, np.nan), std, upper.astype(int))
    if mean.shape[0] < 2:
        raise TooFewAnchorsError(f"{mean.shape[0]} anchors: a calibration needs at least 3")
    off_diagonal = ~np.eye(mean.shape[0], dtype=bool)
    # carried ranges (a RangeMatrix's carry_var_m2) may lie further below zero: the carry's error
    floor = negative_range_floor_m(getattr(matrix, "carry_var_m2", None))
    negative = (mean < floor) & off_diagonal  # NaN compares False
    if negative.any():
        i, j = np.argwhere(negative)[0]
        below = -np.broadcast_to(floor, mean.shape)[i, j]
        raise InvalidRangeError(
            f"range ({i}, {j}) = {mean[i, j]!r}: negative beyond the noise of a corrected range "
            f"(-{below:.3g} m: {NEGATIVE_RANGE_TOLERANCE_M} m, plus the carry's error where the range was "
            f"carried); raw ranges must be corrected first")
    if range_std_m is not None:
        pairs, dist, var = matrix.symmetric(std_m=float(range_std_m))
    else:
        pairs, dist, var = matrix.symmetric(min_std_m=min_range_std_m)
    if not np.all((var > 0) & np.isfinite(var)):
        raise InvalidRangeError("range variances must be finite and > 0: check the stds and counts")
    if len(pairs) == 0:
        raise DisconnectedGraphError("no pair was measured")
    return pairs, dist, var, mean.shape[0]


def _check_connected(pairs: np.ndarray, n: int) -> None:
    # Union-find: for a few dozen anchors this is far cheaper than scipy.sparse.csgraph.
    parent = list(range(n))

    def root(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for i, j in pairs.tolist():
        parent[root(i)] = root(j)
    roots = [root(a) for a in range(n)]
    if len(set(roots)) > 1:
        groups = [[a for a in range(n) if roots[a] == r] for r in dict.fromkeys(roots)]
        raise DisconnectedGraphError(f"range graph has {len(groups)} disconnected components: {groups}")


@lru_cache(maxsize=64)
def _complete_structure(n: int, dim: int, refs: tuple[int, ...]) -> PairStructure:
    return pair_structure(_pair_index(n)[0], n, dim, _free_mask(n, dim, refs))


def _structure(pairs: np.ndarray, n: int, dim: int, refs: tuple[int, ...]) -> PairStructure:
    if pairs is _pair_index(n)[0]:  # every pair measured: the usual round, keyed cheaply
        return _complete_structure(n, dim, refs)
    return pair_structure(pairs, n, dim, _free_mask(n, dim, refs))


def _free_mask(n: int, dim: int, refs: tuple[int, ...]) -> np.ndarray:
    """Coordinates the solver estimates; the gauge anchors' fixed ones are excluded."""
    free = np.ones((n, dim), dtype=bool)
    for level, anchor in enumerate(refs[:dim]):
        free[anchor, level:] = False  # origin: all fixed; +x ref: y(,z) fixed; +y ref (3D): z fixed
    return free.ravel()


def _gauge_refs(prior: np.ndarray) -> tuple[int, ...]:
    """Anchor 0, the anchor farthest from it (+x), and in 3D the one farthest off that axis."""
    b = int(np.argmax(np.linalg.norm(prior - prior[0], axis=1)))
    if b == 0:
        raise GeometryError("prior anchors all coincide: the frame cannot be fixed")
    return frame_refs(prior, 0, b)


# -- initializers ------------------------------------------------------------------------------
def _initial_positions(pairs, dist, n, dim, initializer):
    all_pairs, upper, lower = _pair_index(n)
    if pairs is not all_pairs:
        upper, lower = pairs[:, 0] * n + pairs[:, 1], pairs[:, 1] * n + pairs[:, 0]
    full = np.full((n, n), np.nan)
    full.put(upper, dist)
    full.put(lower, dist)
    full.flat[:: n + 1] = 0.0
    if initializer in ("auto", "trilateration"):
        try:
            return trilaterate_initial(full, dim), "trilateration"
        except GeometryError:
            if initializer == "trilateration":
                raise
    return classical_mds(full, dim), "mds"


def trilaterate_initial(full: np.ndarray, dim: int) -> np.ndarray:
    """The paper's first-calibration start: anchors from their ranges to anchors 0 and 1.

    Anchor 0 at the origin, 1 on +x, |y| = sqrt(d0k^2 - x_k^2). In 2D the anchor farthest off the
    x axis is placed at +y, every other anchor takes the y sign that fits its range to that one,
    then (with 5+ anchors) the sign that best fits its ranges to all the others as placed by
    that first pass; the mirror image is settled afterwards by the frame's sign rule. In 3D
    anchors are placed in turn, each with the z sign that fits the anchors already placed.
    """
    n = full.shape[0]
    needed = [0, 1, 2] if dim == 3 else [0, 1]
    if np.isnan(full[: len(needed)].sum()):
        raise GeometryError(f"trilateration needs every range to anchors {needed}")
    d01 = full[0, 1]
    scale = float(np.fmax.reduce(full, axis=None))  # max ignoring NaN (nanmax is slower)
    if d01 < 1e-3 * scale:
        raise GeometryError(f"anchors 0 and 1 are {d01:.3g} m apart: cannot define the x axis")
    if dim == 2:
        return _trilaterate_2d(full, d01, scale)
    x = np.zeros((n, dim))
    x[1, 0] = d01
    for k in range(2, n):
        xk = (full[0, k] ** 2 - full[1, k] ** 2 + d01**2) / (2 * d01)
        rest2 = max(full[0, k] ** 2 - xk**2, 0.0)
        x[k] = _best_candidate(_trilaterate_3d(full, x, k, xk, rest2, scale), full[k, :k], x[:k])
    if np.abs(x[:, 2]).max() < 1e-3 * scale:
        # noise drove every z under the root to zero: a flat start is no 3D start (MDS takes over)
        raise GeometryError("trilateration placed every anchor in one plane")
    return x


def _trilaterate_2d(full: np.ndarray, d01: float, scale: float) -> np.ndarray:
    d0sq = full[0] * full[0]
    xs = (d0sq - full[1] * full[1] + d01 * d01) / (2 * d01)
    ys = np.sqrt(np.maximum(d0sq - xs * xs, 0.0))
    xs[:2] = 0.0, d01  # exactly, not up to rounding: these are the gauge's fixed coordinates
    ys[:2] = 0.0
    if ys[2:].max() < 1e-6 * scale:
        raise GeometryError("anchors are collinear: trilateration cannot place them off the x axis")
    if len(xs) > 3:
        # Mirror candidates (x, +y) and (x, -y): keep the one that better fits the range to the
        # anchor farthest off the x axis (taken at +y; the final sign rule picks the mirror).
        ref = 2 + int(np.argmax(ys[2:]))
        dx = xs - xs[ref]
        flip = np.abs(np.hypot(dx, ys + ys[ref]) - full[ref]) < np.abs(np.hypot(dx, ys - ys[ref]) - full[ref])
        flip[:2] = False
        flip[ref] = False
        ys[flip] *= -1.0
    if len(xs) > 4:
        # Second pass: the sign that best fits the ranges to all other anchors as placed by the
        # first (points as complex numbers; the diagonal and missing ranges count nothing).
        n = len(xs)
        placed = xs + 1j * ys
        up = xs + 1j * np.abs(ys)
        misfit_up = np.abs(up[:, None] - placed) - full
        misfit_down = np.abs(up.conj()[:, None] - placed) - full
        misfit_up.flat[:: n + 1] = 0.0
        misfit_down.flat[:: n + 1] = 0.0
        # fmax: a missing range (NaN) costs 0
        cost_up = np.add.reduce(np.fmax(misfit_up * misfit_up, 0.0), 1)
        cost_down = np.add.reduce(np.fmax(misfit_down * misfit_down, 0.0), 1)
        sign = np.where(cost_down < cost_up, -1.0, 1.0)
        sign[:2] = sign[ref] = 1.0  # the reference stays at +y
        ys = np.abs(ys) * sign
    x = np.empty((len(xs), 2))
    x[:, 0], x[:, 1] = xs, ys
    return x


def _trilaterate_3d(full, x, k, xk, rest2, scale):
    if k == 2:
        return np.array([[xk, np.sqrt(rest2), 0.0]])
    x2, y2 = x[2, 0], x[2, 1]
    if abs(y2) < 1e-6 * scale:  # relative: rounding leaves ~1e-8 of a collinear anchor's y
        raise GeometryError("anchors 0, 1, 2 are collinear: cannot fix the 3D frame")
    yk = (full[0, k] ** 2 - full[2, k] ** 2 + x2**2 + y2**2 - 2 * xk * x2) / (2 * y2)
    zk = np.sqrt(max(full[0, k] ** 2 - xk**2 - yk**2, 0.0))
    return np.array([[xk, yk, zk], [xk, yk, -zk]])


def _best_candidate(candidates, ranges_to_placed, placed):
    if len(candidates) == 1:
        return candidates[0]
    ok = np.isfinite(ranges_to_placed)
    errs = [np.nansum((np.linalg.norm(placed[ok] - c, axis=1) - ranges_to_placed[ok]) ** 2) for c in candidates]
    return candidates[int(np.argmin(errs))]


def classical_mds(full: np.ndarray, dim: int) -> np.ndarray:
    """Classical MDS on the range matrix (missing entries filled by shortest paths)."""
    filled = _shortest_path_filled(full)
    if not np.all(np.isfinite(filled)):
        raise GeometryError("the measured pairs do not connect every anchor: no MDS start")
    n = filled.shape[0]
    centering = np.eye(n) - 1.0 / n
    gram = -0.5 * centering @ (filled**2) @ centering
    vals, vecs = np.linalg.eigh(gram)
    order = np.argsort(vals)[::-1][:dim]
    if vals[order[-1]] <= 1e-9 * max(vals[order[0]], 1e-300):
        raise GeometryError(f"anchors span fewer than {dim} dimensions (collinear or coplanar)")
    return vecs[:, order] * np.sqrt(vals[order])


def horizontal_ranges(mean_m: np.ndarray, heights_m: np.ndarray) -> np.ndarray:
    """(N, N) horizontal parts sqrt(r^2 - dz^2) of pair ranges ``mean_m`` between anchors at
    ``heights_m`` (0 where a range is shorter than the height difference; NaN stays NaN)."""
    dz = heights_m[:, None] - heights_m[None, :]
    with np.errstate(invalid="ignore"):
        flat = np.sqrt(np.maximum(mean_m**2 - dz**2, 0.0))
    return np.where(np.isfinite(mean_m), flat, np.nan)


def calibrate_anchors_known_heights(ranges: RangeMatrix, heights_m: np.ndarray, height_std_m: np.ndarray | float,
                                    *, mark_ambiguous: bool = True, **kwargs) -> CalibrationResult:
    """A 3D calibration whose heights come from elsewhere (the on-board estimates, an
    altimeter): each range becomes its horizontal part, sqrt(r^2 - dz^2) (0 where the range is
    shorter than the height difference), the plane is calibrated in 2D by
    :func:`calibrate_anchors` (``kwargs``: its arguments, ``dim`` excluded) and the heights are
    attached with variance ``height_std_m^2``. For anchors at similar heights, whose ranges fit
    a flat shape within their noise: the ranges cannot fix the heights then. The result is
    marked ``ambiguous`` (the ranges alone did not decide the shape), unless
    ``mark_ambiguous=False``: heights that are known (measured mount heights), not a fallback,
    leave the plane's own verdict."""
    heights = np.asarray(heights_m, dtype=float)
    n = ranges.n_anchors
    if heights.shape != (n,) or not np.isfinite(heights).all():
        raise InvalidRangeError(f"heights_m: expected ({n},) finite heights, got shape {heights.shape}")
    std = np.broadcast_to(np.asarray(height_std_m, dtype=float), (n,))
    if not np.all(np.isfinite(std) & (std >= 0)):
        raise SolverArgumentError(f"height_std_m={height_std_m!r}: must be finite and >= 0")
    plane = calibrate_anchors(replace(ranges, mean_m=horizontal_ranges(ranges.mean_m, heights)), dim=2, **kwargs)
    cov = np.zeros((n, 3, n, 3))
    cov[:, :2, :, :2] = plane.covariance.reshape(n, 2, n, 2)
    cov[np.arange(n), 2, np.arange(n), 2] = std**2
    return replace(plane, positions=np.column_stack([plane.positions, heights]), covariance=cov.reshape(3 * n, 3 * n),
                   message=f"heights given, plane from the ranges: {plane.message}",
                   ambiguous=True if mark_ambiguous else plane.ambiguous)
