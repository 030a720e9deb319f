"""Is a calibration's covariance honest in the env? NEES of later calibrations (issue: localization
that never passes a wrong answer off as a success).

``bench_localization`` checks the solver on static rounds with Gaussian ranges (NEES 1.00 at
N = 8). In the env the rounds are ranged while the robots move (each pair's mean is carried to
the round's midpoint along the odometry) and the ranges have NLOS outliers; this measures what
that leaves of the covariance's honesty. For each configuration, episodes with a team round
every 10 steps; every later round is solved by the full solver (``later_calibrations`` hands
every team back: the same answers, ``tests/test_batched_calibration.py``) and each round that
comes back ``ok`` and unambiguous is scored:

    NEES = e^T C^+ e,   e = estimate - truth, both in the paper frame of the round's gauge
    anchors (the frame's sign convention, which near-degenerate layouts can flip, is taken
    from the estimate), C the solver's covariance in that frame.

This scores the shape and its covariance in the round's own gauge, not where the round puts
the team in the running frame. Only rounds reported ok and unambiguous are scored, so the
figures are lower bounds. Rounds of one episode share its layout and motion, so each mean's
95 % interval (``*_ci95_low`` / ``*_ci95_high``) resamples whole episodes (a cluster bootstrap,
2,000 draws; 30 episodes per configuration, ``--episodes``).

An honest covariance gives a mean NEES equal to its rank, N dim - dim (dim + 1) / 2, and 0.1 %
of rounds beyond the chi-square 99.9 % quantile. Figures per configuration (``<cfg>`` =
``{2d,3d}_n<N>_{static,patrol}_{clean,nlos}``): ``nees_over_rank_<cfg>`` (mean NEES / rank),
``nees_median_over_rank_<cfg>``, ``nees_beyond_999_share_<cfg>``, ``rounds_<cfg>``, and the
scored rounds' anchor RMSE in the gauge frame, ``shape_rmse_m_<cfg>`` (what the NEES weighs).

Which of the two is off when the NEES is: the ranges' chi-square at the true shape minus at the
fit, ``truth_chi2_gap_over_rank_<cfg>`` (mean / rank). For Gaussian ranges with the variance
the solver assumes it is chi-square with rank degrees of freedom (the likelihood ratio), so
about 1 whatever the likelihood's shape. A gap near 1 with a NEES well above it says the
likelihood is honest and its *linearization* (the covariance) is not: a likelihood far from
quadratic, e.g. heights of near-coplanar anchors in 3D. A gap well above 1 says the ranges'
model (variance, outliers, motion during the round) is off. ``ambiguous_share_<cfg>``: of
the later rounds reported ok, the share flagged ambiguous (left out of the scores above; the
env applies them all the same); ``nees_over_rank_all_ok_<cfg>`` and
``shape_rmse_m_all_ok_<cfg>`` count them in. ``worst_nees_over_rank_<cfg>`` and
``worst_truth_chi2_gap_<cfg>``: the ok round with the largest NEES, and its chi-square gap.

    python benchmarks/bench_consistency.py [--quick]

Writes benchmarks/results/bench_consistency.json (``_quick`` with --quick).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import print_table, write_results  # noqa: E402

# (dim, anchors, anchor motion, NLOS probability (None: the default radio))
CONFIGS = (
    (2, 5, "static", 0.0), (2, 5, "patrol", 0.0), (2, 5, "patrol", None), (2, 4, "patrol", None),
    (3, 8, "static", 0.0), (3, 8, "patrol", 0.0), (3, 8, "patrol", None),
)
SEED_BASE = 700_000  # outside the protocol's training / validation / test blocks


def name_of(dim: int, n: int, motion: str, nlos) -> str:
    return f"{dim}d_n{n}_{motion}_{'clean' if nlos == 0.0 else 'nlos'}"


def run_config(dim: int, n: int, motion: str, nlos, episodes: int, steps: int) -> dict:
    """Of every later round of ``episodes`` episodes reported ok: its NEES, mean squared anchor
    error (m^2), the truth's chi-square minus the fit's, and whether it was flagged ambiguous
    (arrays under those keys)."""
    import uwb_env.team_state as team_state  # the later rounds' solve (both envs)
    from uwb_env import parallel_env
    from uwb_env.localization.bounds import gauge_nees

    rounds = []
    current = {}
    solve, batched = team_state.calibrate_anchors, team_state.later_calibrations

    def recording_solve(*args, **kwargs):
        result = solve(*args, **kwargs)
        s = current.get("system")
        if s is not None and kwargs.get("prior") is not None and result.status == "ok":
            truth = s.world.to_estimate_frame(s._round_path.midpoint_truth())
            fitted = np.linalg.norm(truth[result.pairs[:, 0]] - truth[result.pairs[:, 1]], axis=1)
            truth_chi2 = float(np.sum((fitted - result.ranges_m) ** 2 / result.range_var_m2))
            rounds.append((result.positions.copy(), result.covariance.copy(), tuple(result.gauge_refs), truth,
                           truth_chi2 - result.chi2, bool(result.ambiguous), current["episode"]))
        return result

    def hand_back_all(*args, **kwargs):
        solved = batched(*args, **kwargs)
        solved.hand_back(np.arange(len(solved)))
        return solved

    sim = {"dim": dim, "n_anchors": n, "anchor_motion": {"model": motion}}
    if nlos is not None:
        sim["ranging"] = {"nlos_probability": nlos, "dropout_probability": 0.0}
    team_state.calibrate_anchors, team_state.later_calibrations = recording_solve, hand_back_all
    try:
        for seed in range(SEED_BASE, SEED_BASE + episodes):
            env = parallel_env(sim=sim, max_cycles=steps)
            env.reset(seed=seed)
            current["system"], current["episode"] = env.system, seed - SEED_BASE
            for t in range(steps):
                env.step({a: int(t % 10 == 0) for a in env.agents})
            current.clear()
    finally:
        team_state.calibrate_anchors, team_state.later_calibrations = solve, batched
    out = {"nees": [], "sq": [], "gap": [], "ambiguous": [], "episode": []}
    for x, cov, refs, truth, chi2_gap, ambiguous, episode in rounds:
        value, err = gauge_nees(x, cov, refs, truth)
        out["nees"].append(value)
        out["sq"].append(float(np.sum(err**2)) / n)
        out["gap"].append(chi2_gap)
        out["ambiguous"].append(ambiguous)
        out["episode"].append(episode)
    return {k: np.array(v) for k, v in out.items()}


def episode_bootstrap(values: np.ndarray, episodes: np.ndarray, draws: int = 2000, seed: int = 0) -> tuple:
    """95 % percentile interval of the mean of ``values`` (one per round) resampling whole
    episodes (the rounds of one episode are not independent); NaNs without rounds."""
    ids = np.unique(episodes)
    if len(ids) < 2:
        return float("nan"), float("nan")
    sums = np.array([values[episodes == e].sum() for e in ids])
    counts = np.array([np.sum(episodes == e) for e in ids], dtype=float)
    pick = np.random.default_rng(seed).integers(0, len(ids), (draws, len(ids)))
    means = sums[pick].sum(1) / np.maximum(counts[pick].sum(1), 1.0)
    return float(np.percentile(means, 2.5)), float(np.percentile(means, 97.5))


def main() -> None:
    from scipy.stats import chi2

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--episodes", type=int, default=None, help="episodes per configuration (30; 2 with --quick)")
    a = p.parse_args()
    episodes, steps = (2, 100) if a.quick else (30, 300)
    episodes = a.episodes or episodes
    started = time.perf_counter()
    figures, rows = {"episodes_per_config": episodes, "steps_per_episode": steps}, []
    for dim, n, motion, nlos in CONFIGS:
        every = run_config(dim, n, motion, nlos, episodes, steps)
        scored = ~every["ambiguous"]
        nees, sq, gap = every["nees"][scored], every["sq"][scored], every["gap"][scored]
        clusters = every["episode"][scored]
        rank = n * dim - dim * (dim + 1) // 2
        cfg = name_of(dim, n, motion, nlos)
        over = float(nees.mean() / rank) if len(nees) else float("nan")
        median = float(np.median(nees) / rank) if len(nees) else float("nan")
        beyond = float(np.mean(nees > chi2.ppf(0.999, rank))) if len(nees) else float("nan")
        rmse = float(np.sqrt(sq.mean())) if len(sq) else float("nan")
        gap_over = float(gap.mean() / rank) if len(gap) else float("nan")
        ambiguous = float(every["ambiguous"].mean()) if len(every["nees"]) else float("nan")
        over_all = float(every["nees"].mean() / rank) if len(every["nees"]) else float("nan")
        worst = int(np.argmax(every["nees"])) if len(every["nees"]) else None
        figures.update({f"nees_over_rank_{cfg}": over, f"nees_median_over_rank_{cfg}": median,
                        f"nees_beyond_999_share_{cfg}": beyond, f"rounds_{cfg}": len(nees),
                        f"shape_rmse_m_{cfg}": rmse, f"truth_chi2_gap_over_rank_{cfg}": gap_over,
                        f"ambiguous_share_{cfg}": ambiguous, f"nees_over_rank_all_ok_{cfg}": over_all,
                        f"shape_rmse_m_all_ok_{cfg}": float(np.sqrt(every["sq"].mean())) if len(every["sq"]) else None,
                        f"worst_nees_over_rank_{cfg}": None if worst is None else float(every["nees"][worst] / rank),
                        f"worst_truth_chi2_gap_{cfg}": None if worst is None else float(every["gap"][worst])})
        low, high = episode_bootstrap(nees / rank, clusters)
        gap_low, gap_high = episode_bootstrap(gap / rank, clusters)
        figures.update({f"nees_over_rank_{cfg}_ci95_low": low, f"nees_over_rank_{cfg}_ci95_high": high,
                        f"truth_chi2_gap_over_rank_{cfg}_ci95_low": gap_low,
                        f"truth_chi2_gap_over_rank_{cfg}_ci95_high": gap_high})
        rows.append([cfg, len(nees), ambiguous, rank, f"{over:.2f} [{low:.2f}, {high:.2f}]", over_all, median, beyond,
                     f"{gap_over:.2f} [{gap_low:.2f}, {gap_high:.2f}]", rmse])
    figures["bench_seconds"] = time.perf_counter() - started
    print_table("later calibrations in the env: NEES / rank (1 = honest), share beyond the 99.9 % quantile",
                ["config", "rounds", "ambiguous", "rank", "mean/rank", "all ok", "median/rank", "beyond 99.9 %",
                 "truth chi2 gap/rank", "shape RMSE m"], rows)
    write_results("bench_consistency_quick" if a.quick else "bench_consistency", figures, a.quick)


if __name__ == "__main__":
    main()
