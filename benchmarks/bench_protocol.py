"""The evaluation protocol on one scenario: tuned heuristics, learned policy, lookahead reference.

1. Tunes every heuristic family on validation seeds for the env's return (``uwb-env tune``),
   unless ``--tuned FILE`` gives a tuning result.
2. Evaluates on test seeds (>= 100 by default): the learned policy, the tuned heuristics, the
   ground-truth lookahead planner (built on the tuned fixed interval) and the fixed-interval
   sweep (for the matched-budget point).
3. Reports IQM with bootstrap CIs, the catastrophic rate, the paired IQM difference learned vs
   the best tuned heuristic, and the fraction of the heuristic-to-lookahead gap the learned
   policy closes.

Writes benchmarks/results/bench_protocol.json (``--quick``: bench_protocol_quick.json, few
seeds, short episodes; a smoke run, not a result) and the evaluation's files into ``--out``.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._common import print_table, write_results  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def code_version() -> str:
    try:
        return subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                              text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="8 test seeds, 200-step episodes: a smoke run")
    p.add_argument("--test-seeds", type=int, default=100)
    p.add_argument("--val-seeds", type=int, default=24, help="validation episodes per tuning candidate")
    p.add_argument("--tuned", default=None, help="a `uwb-env tune` result to use instead of tuning here")
    p.add_argument("--learned", default="learned:ppo_scheduler")
    p.add_argument("--lookahead", default="lookahead", help="planner spec (default: on the tuned fixed "
                   "interval K, branches cut at 2.5K steps (60..300): lookahead:2.5K@K)")
    p.add_argument("--config", default=None, help="scenario (YAML/JSON EnvConfig overrides)")
    p.add_argument("--max-cycles", type=int, default=500)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--out", default=str(ROOT / "runs" / "bench_protocol"))
    a = p.parse_args()
    if a.quick:
        a.test_seeds, a.val_seeds, a.max_cycles = 8, 3, 200

    from uwb_env.training import evaluate, tune

    from uwb_env.evaluation.stats import gap_closed_fraction

    start = time.perf_counter()
    out = Path(a.out)
    tuned_path = a.tuned
    if tuned_path is None:
        tuned_path = str(out / "tuned.json")
        tune.main(tune.Args(seeds=a.val_seeds, max_cycles=a.max_cycles, config=a.config, workers=a.workers,
                            out=tuned_path, refine_rounds=0 if a.quick else 2))
    tuned = tune.load_tuned(tuned_path)
    tune_wall = time.perf_counter() - start
    best = tuned["best_tuned_heuristic"]
    lookahead = a.lookahead
    if lookahead == "lookahead" and "fixed" in tuned["tuned"]:
        # The planner improves on the tuned fixed interval K; a branch's cycle lasts up to ~2K steps.
        k = int(tuned["tuned"]["fixed"].partition(":")[2])
        lookahead = f"lookahead:{min(max(60, int(2.5 * k)), 300)}@{k}"
    results = evaluate.main(evaluate.Args(
        policies=[a.learned, lookahead], seeds=a.test_seeds, max_cycles=a.max_cycles, config=a.config,
        tuned=tuned_path, workers=a.workers, out=str(out / "eval"), sweep=True, progress=True))
    wall = time.perf_counter() - start
    rows = {r["policy"]: r for r in results["summary"]}
    learned, heuristic, planner = rows[a.learned], rows[best], rows[lookahead]
    figures = {"n_test_seeds": len(results["seeds"]), "test_seeds_first": results["seeds"][0],
               "validation_seeds_first": tuned["validation_seeds"][0], "best_tuned_heuristic": best,
               "lookahead_spec": lookahead, "learned_spec": a.learned, "scenario": a.config or "default",
               "max_cycles": a.max_cycles, "code_version": code_version(), "wall_s": wall,
               "tuning_wall_s": tune_wall}
    for name, row in (("learned", learned), ("best_tuned_heuristic", heuristic), ("lookahead", planner)):
        figures |= {f"{name}_iqm_tag_error_m": row["iqm_tag_error_m"],
                    f"{name}_iqm_ci_low_m": row["iqm_tag_error_ci_low_m"],
                    f"{name}_iqm_ci_high_m": row["iqm_tag_error_ci_high_m"],
                    f"{name}_median_tag_error_m": row["median_tag_error_m"],
                    f"{name}_mean_tag_error_m": row["mean_tag_error_m"],
                    f"{name}_catastrophic_rate": row["catastrophic_rate"],
                    f"{name}_catastrophic_ci_high": row["catastrophic_rate_ci_high"],
                    f"{name}_calibrations_per_min": row["calibrations_per_min"], f"{name}_return": row["return"]}
    figures |= {"learned_vs_best_heuristic_paired_diff_m": learned["iqm_diff_vs_reference_m"],
                "learned_vs_best_heuristic_paired_diff_ci_low_m": learned["iqm_diff_ci_low_m"],
                "learned_vs_best_heuristic_paired_diff_ci_high_m": learned["iqm_diff_ci_high_m"],
                "learned_vs_best_heuristic_significant": learned["significant_vs_reference"],
                "learned_prob_better_than_best_heuristic": learned["prob_better_than_reference"],
                "lookahead_vs_best_heuristic_paired_diff_m": planner["iqm_diff_vs_reference_m"],
                "lookahead_vs_best_heuristic_significant": planner["significant_vs_reference"],
                "gap_closed_fraction": gap_closed_fraction(heuristic["iqm_tag_error_m"], learned["iqm_tag_error_m"],
                                                           planner["iqm_tag_error_m"])}
    matched = results["matched_budget"].get(a.learned)
    if matched:
        figures |= {"fixed_iqm_at_learned_rate_m": matched["fixed_iqm_at_matched_rate_m"],
                    "fixed_iqm_at_learned_rate_ci_low_m": matched["ci_low_m"],
                    "fixed_iqm_at_learned_rate_ci_high_m": matched["ci_high_m"]}
    figures = {k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in figures.items()}
    print_table(f"Protocol benchmark ({figures['n_test_seeds']} test seeds, {a.max_cycles} steps, "
                f"wall {wall:.0f} s)", ["policy", "IQM (m)", "95% CI", "catastrophic", "cal/min", "return"],
                [[f"{name} = {row['policy']}", row["iqm_tag_error_m"],
                  f"[{row['iqm_tag_error_ci_low_m']:.3f}, {row['iqm_tag_error_ci_high_m']:.3f}]",
                  f"{row['catastrophic_rate']:.1%}", row["calibrations_per_min"], row["return"]]
                 for name, row in (("learned", learned), ("best tuned", heuristic), ("lookahead (GT)", planner))])
    print(f"learned - best tuned heuristic (IQM, paired): {learned['iqm_diff_vs_reference_m']:+.3f} m "
          f"[{learned['iqm_diff_ci_low_m']:+.3f}, {learned['iqm_diff_ci_high_m']:+.3f}]"
          f"{' significant' if learned['significant_vs_reference'] else ' not significant'}; "
          f"gap closed: {figures['gap_closed_fraction']}")
    write_results("bench_protocol_quick" if a.quick else "bench_protocol", figures, quick=a.quick)


if __name__ == "__main__":
    main()
