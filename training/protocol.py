"""The evaluation protocol's comparison: per-policy statistics with CIs, paired verdicts
against the reference heuristic, matched-budget interpolation (see
``shared/reference/evaluation-protocol.md``; statistics in :mod:`uwb_env.evaluation.stats`).

Works on the episode records of :func:`uwb_env.training.evaluate.run_episode` (one dict per
policy and seed); comparisons pair episodes by seed.
"""

from __future__ import annotations

import numpy as np

from uwb_env.evaluation import stats

ERROR_KEY = "mean_tag_error_m"  # the per-episode value the statistics are taken of

# One line per column of the comparison table (printed under it).
LEGEND = (
    "IQM [95% CI]: interquartile mean of the per-episode mean tag error (m), bootstrap CI over seeds",
    "median: median episode (m); mean: plain mean, sensitive to failed episodes (m)",
    "catastr.: share of episodes whose mean tag error exceeds 1 m, Wilson 95% CI",
    "cal/min: calibration rounds started per minute; return: the env's episode return (prices the budget)",
    "dIQM vs REF [CI]: IQM(policy) - IQM(reference) paired by seed; * = CI excludes 0 (significant), "
    "- = lower error than the reference",
    "P(better): probability that an episode of the policy has a lower error than the reference's",
    "(GT) reads ground truth: a reference from above, not deployable",
)


def _by_seed(episodes: list[dict], spec: str) -> dict[int, dict]:
    return {e["seed"]: e for e in episodes if e["policy"] == spec}


def policy_statistics(episodes: list[dict], spec: str) -> dict[str, float]:
    """IQM, median and mean tag error with CIs and the catastrophic rate of one policy."""
    values = np.array([e[ERROR_KEY] for e in sorted(_by_seed(episodes, spec).values(), key=lambda e: e["seed"])])
    summary = stats.summarize_errors(values)
    row = {}
    for name, est in summary.items():
        key = "catastrophic_rate" if name == "catastrophic" else f"{name}_tag_error"
        suffix = "" if name == "catastrophic" else "_m"
        row[key + suffix] = est.value
        row[f"{key}_ci_low{suffix}"] = est.ci_low
        row[f"{key}_ci_high{suffix}"] = est.ci_high
    return row


def paired(episodes: list[dict], spec: str, reference: str) -> dict[str, float]:
    """The policy against ``reference`` on their shared seeds: IQM difference and P(better)."""
    mine, ref = _by_seed(episodes, spec), _by_seed(episodes, reference)
    seeds = sorted(set(mine) & set(ref))
    if len(seeds) < 2:
        raise ValueError(f"policies {spec!r} and {reference!r} share {len(seeds)} seeds: need >= 2 to pair")
    a = np.array([mine[s][ERROR_KEY] for s in seeds])
    b = np.array([ref[s][ERROR_KEY] for s in seeds])
    diff = stats.paired_difference(a, b, "iqm")
    poi = stats.probability_of_improvement(a, b)
    return {"vs_reference": reference, "iqm_diff_vs_reference_m": diff.value,
            "iqm_diff_ci_low_m": diff.ci_low, "iqm_diff_ci_high_m": diff.ci_high,
            "significant_vs_reference": bool(diff.excludes_zero()) if spec != reference else False,
            "prob_better_than_reference": poi.value}


def matched_budget(episodes: list[dict], spec: str, family: str = "fixed", statistic: str = "iqm"):
    """The ``family`` sweep's error interpolated at ``spec``'s calibration rate (on shared
    seeds), as an :class:`~uwb_env.evaluation.stats.Estimate`; None without a sweep."""
    sweep = sorted({e["policy"] for e in episodes if e["policy"].partition(":")[0] == family})
    target = _by_seed(episodes, spec)
    per = [_by_seed(episodes, s) for s in sweep]
    seeds = sorted(set(target).intersection(*per)) if per else []
    if len(sweep) < 2 or len(seeds) < 2:
        return None
    rates = np.array([[p[s]["calibrations_per_min"] for s in seeds] for p in per])
    errors = np.array([[p[s][ERROR_KEY] for s in seeds] for p in per])
    return stats.matched_budget(rates, errors, [target[s]["calibrations_per_min"] for s in seeds], statistic)


def best_heuristic(summary: list[dict], candidates: list[str] | None = None) -> str | None:
    """The heuristic with the highest mean return among ``candidates`` (default: every policy
    that reads no ground truth and is not learned)."""
    rows = [r for r in summary if not r["uses_ground_truth"] and r["policy"].partition(":")[0] not in
            ("learned", "rllib") and (candidates is None or r["policy"] in candidates)]
    return max(rows, key=lambda r: r["return"])["policy"] if rows else None


def format_comparison(summary: list[dict], only_main: bool = True) -> str:
    rows = [r for r in summary if r["group"] == "main" or not only_main]
    reference = next((r.get("vs_reference") for r in rows if r.get("vs_reference")), None)

    def ci(r, key):
        return f"{r[key + '_m']:.3f} [{r[key + '_ci_low_m']:.3f}, {r[key + '_ci_high_m']:.3f}]"

    head = ["policy", "IQM [95% CI]", "median", "mean", "catastr. [CI]", "cal/min", "return"]
    if reference:
        head += [f"dIQM vs {reference} [CI]", "P(better)"]
    cells = [head]
    for r in rows:
        line = [r["policy"] + (" (GT)" if r["uses_ground_truth"] else "") + (" (REF)" if r["policy"] == reference
                                                                              else ""),
                ci(r, "iqm_tag_error"), f"{r['median_tag_error_m']:.3f}", f"{r['mean_tag_error_m']:.3f}",
                f"{r['catastrophic_rate']:.0%} [{r['catastrophic_rate_ci_low']:.0%}, "
                f"{r['catastrophic_rate_ci_high']:.0%}]",
                f"{r['calibrations_per_min']:.1f}", f"{r['return']:.1f}"]
        if reference:
            if r.get("vs_reference") and r["policy"] != reference:
                line += [f"{r['iqm_diff_vs_reference_m']:+.3f} [{r['iqm_diff_ci_low_m']:+.3f}, "
                         f"{r['iqm_diff_ci_high_m']:+.3f}]{' *' if r['significant_vs_reference'] else '  '}",
                         f"{r['prob_better_than_reference']:.2f}"]
            else:
                line += ["-", "-"]
        cells.append(line)
    widths = [max(len(c[i]) for c in cells) for i in range(len(head))]
    lines = ["  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(row, widths, strict=True)))
             for row in cells]
    lines.insert(1, "-" * len(lines[0]))
    legend = [line.replace("REF", reference or "the reference") for line in LEGEND
              if not line.startswith("(GT)") or any(r["uses_ground_truth"] for r in rows)]
    return "\n".join(lines + [""] + legend)
