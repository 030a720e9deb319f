"""Evaluation harness: run calibration schedulers over held-out seeds and compare them.

Usage (also ``uwb-env evaluate``)::

    python -m uwb_env.training.evaluate --policies fixed:10 threshold:0.15 oracle --seeds 8 --workers 2

Per policy it reports tag error (mean, median, p95), anchor error, calibrations per minute,
fraction of time calibrating and return, and writes into ``--out``:

- ``episodes.csv``: one row per (policy, seed);
- ``summary.csv`` / ``summary.json``: per policy, the mean over seeds (plus the standard error
  of the mean tag error);
- ``error_over_time.png``, ``boxplot.png``, ``tradeoff.png`` (with the ``plot`` extra): error
  traces, per-step tag-error distributions, and tag error vs calibration rate for the
  fixed-interval and threshold sweeps beside the single policies.

Seeds: evaluation episodes use ``EVAL_SEED_BASE + i``; training uses seeds below it, so a
learned policy is never evaluated on an episode it trained on.
"""

from __future__ import annotations

import argparse
import csv
import functools
import json
import multiprocessing
import os
import sys
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

EVAL_SEED_BASE = 1_000_000
DEFAULT_POLICIES = ("fixed:10", "threshold:0.15", "residual:0.2", "never", "oracle:0.3")
FIXED_SWEEP_STEPS = (5, 7, 10, 15, 20, 30, 45, 70, 100, 150, 250)
THRESHOLD_SWEEP_M = (0.08, 0.12, 0.2, 0.3, 0.5)
# Tuned specs of the default scenario (``uwb-env tune --out`` this file to refresh it).
DEFAULT_TUNED = Path(__file__).with_name("tuned") / "default.json"
METRICS = ("mean_tag_error_m", "median_tag_error_m", "p95_tag_error_m", "mean_anchor_error_m",
           "calibrations_per_min", "fraction_calibrating", "return")


# The main job's learned entry: the team-size-invariant per-anchor scheduler
# (training/train_anchor_set.py; the training seed with the best validation score).
SHIPPED_LEARNED = "anchor_set"


def shipped_learned_spec(tuned: Path = DEFAULT_TUNED) -> str:
    """``learned:anchor_set@T`` (or ``@drift:T``, ``@team:T``): the shipped residual scheduler on
    the rule tuned for the default scenario: of ``tuned``'s families it can take as its base (the
    per-anchor rules on the predicted std and on the drift since calibration, the team
    threshold) the one with the highest validation return, at its threshold (the model's
    default base when the file has none)."""
    from uwb_env.agents.per_anchor import BASE_FAMILIES, learned_base

    try:
        record = json.loads(Path(tuned).read_text())
        names = [f for f in BASE_FAMILIES if f in record["tuned"]]
        family = max(names, key=lambda f: record.get("families", {}).get(f, {}).get("best_return", -np.inf))
        return f"learned:{SHIPPED_LEARNED}@{learned_base(record['tuned'][family])}"
    except (OSError, KeyError, ValueError):
        return f"learned:{SHIPPED_LEARNED}"


def default_policies() -> list[str]:
    """The baselines, plus the shipped learned scheduler when stable-baselines3 is installed."""
    from uwb_env.agents.registry import shipped_model

    policies = list(DEFAULT_POLICIES)
    try:
        import stable_baselines3  # noqa: F401
    except ImportError:
        return policies
    if shipped_model(SHIPPED_LEARNED).is_file():
        policies.insert(0, shipped_learned_spec())
    return policies


@dataclass
class Args:
    policies: list[str] = field(default_factory=default_policies)
    """policy specs (see ``agents.registry``)"""
    seeds: int = 30
    """evaluation episodes per policy (seeds EVAL_SEED_BASE + seed_offset + i)"""
    seed_offset: int = 0
    max_cycles: int = 500
    """steps per episode"""
    sweep: bool = True
    """add the fixed-interval and threshold sweeps (the trade-off curve)"""
    config: str | None = None
    """YAML/JSON file with EnvConfig overrides (the scenario)"""
    scenarios: list[str] = field(default_factory=list)
    """several scenario files (e.g. training/scenarios/*.yml): each is evaluated into
    ``out/<file stem>/`` and ``out/scenarios.csv`` gathers every summary row; a learned
    policy that does not fit a scenario's observations is left out of it (with a note)"""
    suite: str | None = None
    """run the scenario suite (a suite YAML; "default": training/scenarios/suite/suite.yml)
    with ``seeds`` test seeds per scenario, in parallel; see ``training.suite``"""
    suite_scenarios: list[str] = field(default_factory=list)
    """only these scenarios of the suite"""
    skip_incompatible: bool = False
    """leave out (with a note) policies that cannot act in the env instead of failing"""
    workers: int = 1
    """parallel processes (1 = in this process)"""
    tuned: str | None = None
    """a ``uwb-env tune`` result: its tuned specs join the policies and its best one is the
    reference of the paired verdicts (default: training/tuned/default.json for the default
    scenario; "none" for no file: then the reference is the best heuristic run, untuned)"""
    reference: str | None = None
    """the spec every policy is compared with (overrides the tuned file's best)"""
    out: str | None = "runs/evaluate"
    """output folder (None: write nothing)"""
    plots: bool = True
    progress: bool = True


def _label_group(spec: str) -> str:
    return spec.partition(":")[0]


def sweep_specs() -> list[str]:
    return [f"fixed:{k}" for k in FIXED_SWEEP_STEPS] + [f"threshold:{t}" for t in THRESHOLD_SWEEP_M]


def _env_config(overrides: dict, max_cycles: int):
    from uwb_env.config import EnvConfig

    return EnvConfig.from_dict({**overrides, "max_cycles": max_cycles})


def run_episode(spec: str, seed: int, config_dict: dict) -> dict:
    """One episode of ``spec`` on seed ``seed``; returns its summary and per-step traces."""
    from uwb_env.config import EnvConfig

    config = EnvConfig.from_dict(config_dict)
    policy = _cached_policy(spec, config.sim.dt_s)  # reset() by rollout; a saved model is read once
    return {"policy": spec, **run_policy_episode(policy, seed, config)}


def run_policy_episode(policy, seed: int, config) -> dict:
    """One episode of a policy object on seed ``seed`` (``config``: EnvConfig or overrides dict)."""
    from uwb_env.config import EnvConfig
    from uwb_env.env.parallel_env import UWBCalibrationParallelEnv
    from uwb_env.env.policy import rollout

    if not isinstance(config, EnvConfig):
        config = EnvConfig.from_dict(config)
    mode = getattr(policy, "action_mode", None)
    if mode is not None and mode != config.action_mode:  # same scenario, the actions the policy chooses among
        config = config.replace(action_mode=mode)
    env = UWBCalibrationParallelEnv(config)
    if hasattr(policy, "configure"):  # the scenario's declared parameters (step length), no ground truth
        policy.configure(config)
    if hasattr(policy, "bind"):  # planners on the true state (lookahead) need the env itself
        policy.bind(env)
    result = rollout(env, policy, seed=seed)
    return {
        "seed": seed, "uses_ground_truth": bool(policy.uses_ground_truth),
        **result.summary(), "tag_error_trace": result.tag_error_m, "anchor_error_trace": result.anchor_error_m,
    }


@functools.lru_cache(maxsize=64)
def _cached_policy(spec: str, dt_s: float):
    from uwb_env.agents.registry import make_policy

    return make_policy(spec, dt_s)


def _run_star(job):
    return run_episode(*job)


def run_jobs(jobs: list[tuple], workers: int = 1, label: str = "evaluate", show: bool = True) -> list[dict]:
    """Run ``run_episode(spec, seed, config_dict)`` for every job, in ``workers`` processes."""
    from uwb_env.progress import progress

    if workers == 1:
        return [run_episode(*job) for job in progress(jobs, len(jobs), label, enabled=show)]
    # forkserver, not fork: forking a process that has torch's thread pools running (a
    # learned policy was loaded, or training just ran) can deadlock the children.
    context = multiprocessing.get_context("forkserver")
    with ProcessPoolExecutor(max_workers=workers, mp_context=context) as pool:
        # small chunks: episodes differ 100x in cost (a lookahead planner vs a fixed interval), and
        # big chunks leave one worker with all the expensive ones and the progress line frozen
        it = pool.map(_run_star, jobs, chunksize=max(1, min(4, len(jobs) // (8 * workers))))
        return list(progress(it, len(jobs), label, enabled=show))


def evaluate(args: Args) -> dict:
    """Run every policy on every evaluation seed; write the files; return the results."""
    from uwb_env.cli import load_overrides

    if args.progress:  # at once: loading the policies (torch, SB3) takes seconds
        print("evaluate: loading policies ...", file=sys.stderr, flush=True)
    if args.seeds < 1:
        raise ValueError(f"seeds={args.seeds!r}: must be >= 1")
    if args.workers < 1:
        raise ValueError(f"workers={args.workers!r}: must be >= 1")
    config = _env_config(load_overrides(args.config), args.max_cycles)
    config_dict = config.to_dict()
    tuned = _tuned_record(args)
    main_specs = list(dict.fromkeys(list(args.policies) + (list(tuned["tuned"].values()) if tuned else [])))
    reference = args.reference or (tuned["best_tuned_heuristic"] if tuned else None)
    if reference and reference not in main_specs:
        main_specs.append(reference)
    specs = list(dict.fromkeys(main_specs + (sweep_specs() if args.sweep else [])))
    from uwb_env.agents.registry import make_policy

    for spec in list(specs):  # fail on a bad spec before any work starts
        problem = getattr(make_policy(spec, config.sim.dt_s), "incompatibility", lambda _: None)(config)
        if problem is None:
            continue
        if not args.skip_incompatible:
            raise ValueError(f"policy {spec!r}: {problem}")
        print(f"skipping {spec}: {problem}")
        specs.remove(spec)
    seeds = [EVAL_SEED_BASE + args.seed_offset + i for i in range(args.seeds)]
    jobs = [(spec, seed, config_dict) for spec in specs for seed in seeds]
    if args.progress:
        print(f"evaluate: {len(specs)} policies x {len(seeds)} seeds = {len(jobs)} episodes of {config.max_cycles} "
              f"steps on {args.workers} worker(s)", file=sys.stderr, flush=True)
    episodes = run_jobs(jobs, args.workers, "evaluate", args.progress)
    main_specs = [p for p in main_specs if p in specs]
    if reference is None:
        from uwb_env.training.protocol import best_heuristic

        reference = best_heuristic(summarize(episodes, specs, main_specs, statistics=False), main_specs)
    summary = summarize(episodes, specs, main=main_specs, reference=reference if len(seeds) > 1 else None)
    results = {"summary": summary, "episodes": episodes, "seeds": seeds, "config": config_dict,
               "dt_s": config.sim.dt_s, "reference": reference,
               "reference_kind": "tuned" if tuned and reference == tuned["best_tuned_heuristic"] else
               "given" if args.reference else "best heuristic run (untuned)",
               "tuned_file": tuned.get("path") if tuned else None,
               "matched_budget": _matched_budgets(episodes, main_specs) if args.sweep and len(seeds) > 1 else {}}
    if args.out:
        results["written"] = write_outputs(results, args.out, plots=args.plots)
    return results


def _tuned_record(args: Args) -> dict | None:
    from uwb_env.training.tune import load_tuned

    path = args.tuned
    if path is None and args.config is None and DEFAULT_TUNED.is_file():
        path = str(DEFAULT_TUNED)
    if path is None or path == "none":
        return None
    return {**load_tuned(path), "path": path}


def _matched_budgets(episodes: list[dict], main_specs: Sequence[str]) -> dict[str, dict]:
    """Each learned policy's budget matched on the fixed-interval sweep (IQM, with CI)."""
    from uwb_env.training.protocol import matched_budget

    out = {}
    for spec in main_specs:
        if spec.partition(":")[0] in ("learned", "rllib"):
            est = matched_budget(episodes, spec)
            if est is not None:
                out[spec] = {"fixed_iqm_at_matched_rate_m": est.value, "ci_low_m": est.ci_low, "ci_high_m": est.ci_high}
    return out


def summarize(episodes: list[dict], specs: Sequence[str], main: Sequence[str], reference: str | None = None,
              statistics: bool = True) -> list[dict]:
    """Per policy: means over seeds, plus (``statistics``) the protocol's statistics with CIs
    and, given a ``reference`` spec, the paired verdict against it."""
    from uwb_env.training.protocol import paired, policy_statistics

    rows = []
    for spec in specs:
        mine = [e for e in episodes if e["policy"] == spec]
        row = {"policy": spec, "group": "main" if spec in main else "sweep_" + _label_group(spec),
               "uses_ground_truth": mine[0]["uses_ground_truth"], "episodes": len(mine)}
        for m in METRICS:
            row[m] = float(np.mean([e[m] for e in mine]))
        tag = np.array([e["mean_tag_error_m"] for e in mine])
        row["mean_tag_error_sem_m"] = float(tag.std(ddof=1) / np.sqrt(len(tag))) if len(tag) > 1 else 0.0
        if statistics:
            row.update(policy_statistics(episodes, spec))
            if reference is not None and row["group"] == "main":
                row.update(paired(episodes, spec, reference))
        rows.append(row)
    return rows


def format_table(summary: list[dict], only_main: bool = True) -> str:
    if summary and "iqm_tag_error_m" in summary[0]:
        from uwb_env.training.protocol import format_comparison

        return format_comparison(summary, only_main)
    return _format_means(summary, only_main)


def _format_means(summary: list[dict], only_main: bool = True) -> str:
    cols = [("policy", "policy", "{}"), ("mean_tag_error_m", "tag mean", "{:.3f}"),
            ("median_tag_error_m", "tag med", "{:.3f}"), ("p95_tag_error_m", "tag p95", "{:.3f}"),
            ("mean_anchor_error_m", "anchor", "{:.3f}"), ("calibrations_per_min", "cal/min", "{:.1f}"),
            ("fraction_calibrating", "busy", "{:.1%}"), ("return", "return", "{:.1f}")]
    rows = [r for r in summary if r["group"] == "main" or not only_main]
    cells = [[c[1] for c in cols]] + [
        [fmt.format(r[key]) + (" (GT)" if key == "policy" and r["uses_ground_truth"] else "") for key, _, fmt in cols]
        for r in rows
    ]
    widths = [max(len(row[i]) for row in cells) for i in range(len(cols))]
    lines = ["  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(row, widths, strict=True)))
             for row in cells]
    lines.insert(1, "-" * len(lines[0]))
    notes = "Errors in m; busy = share of time calibrating; return = episode reward sum (higher is better)."
    if any(r["uses_ground_truth"] for r in rows):
        notes += "\n(GT) uses ground truth: a reference, not deployable."
    return "\n".join(lines) + "\n" + notes


def _sig(value, digits: int = 6):
    """Floats to ``digits`` significant digits for the CSVs (5.9, not 5.8999999999999995)."""
    return float(f"{value:.{digits}g}") if isinstance(value, float) else value


def write_outputs(results: dict, out: str, plots: bool = True) -> list[str]:
    os.makedirs(out, exist_ok=True)
    written = []
    ep_path = os.path.join(out, "episodes.csv")
    with open(ep_path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["policy", "seed", "uses_ground_truth", *METRICS])
        for e in results["episodes"]:
            w.writerow([e["policy"], e["seed"], e["uses_ground_truth"], *(_sig(e[m]) for m in METRICS)])
    written.append(ep_path)
    sum_csv = os.path.join(out, "summary.csv")
    keys = list(results["summary"][0])
    with open(sum_csv, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        w.writerows({k: _sig(v) for k, v in row.items()} for row in results["summary"])
    written.append(sum_csv)
    sum_json = os.path.join(out, "summary.json")
    with open(sum_json, "w") as f:
        # the tuned file as printed (the shipped one by name): no install or temporary path in results
        tuned_file = _display_path(results["tuned_file"]) if results.get("tuned_file") else None
        json.dump({"summary": results["summary"], "seeds": results["seeds"], "config": results["config"],
                   **{k: results.get(k) for k in ("reference", "reference_kind", "matched_budget")},
                   "tuned_file": tuned_file}, f, indent=2)
    written.append(sum_json)
    if plots:
        written += write_plots(results, out)
    return written


def write_plots(results: dict, out: str) -> list[str]:
    from uwb_env.training.plots import evaluation_plots

    return evaluation_plots(results, out)


def add_arguments(p: argparse.ArgumentParser) -> None:
    from uwb_env.agents.registry import POLICIES

    d = Args(policies=[])  # the default policy list is resolved at run time (it may import SB3)
    p.add_argument("--policies", nargs="+", default=None, help="policy specs NAME[:PARAM], e.g. fixed:10 "
                   f"threshold:0.15 learned:model.zip; names: {', '.join(POLICIES)} (default: the baselines, "
                   "plus the shipped PPO model when stable-baselines3 is installed)")
    p.add_argument("--seeds", type=int, default=d.seeds, help=f"episodes per policy (default {d.seeds})")
    p.add_argument("--seed-offset", type=int, default=d.seed_offset)
    p.add_argument("--max-cycles", type=int, default=d.max_cycles, help=f"steps per episode (default {d.max_cycles})")
    p.add_argument("--no-sweep", dest="sweep", action="store_false", help="skip the fixed/threshold sweeps")
    p.add_argument("--config", default=None, help="YAML/JSON file with EnvConfig overrides")
    p.add_argument("--scenarios", nargs="+", default=[], help="several scenario files (e.g. "
                   "training/scenarios/*.yml), each evaluated into OUT/<stem>/")
    p.add_argument("--suite", nargs="?", const="default", default=None, metavar="SUITE_YML",
                   help="run the scenario suite (default training/scenarios/suite/suite.yml): per-scenario and "
                   "aggregate tables and a performance profile in OUT")
    p.add_argument("--suite-scenarios", nargs="+", default=[], metavar="NAME", help="only these suite scenarios")
    p.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1), help="parallel processes")
    p.add_argument("--tuned", default=None, help="a `uwb-env tune` result file: adds the tuned heuristics and "
                   "compares every policy with the best of them (default: the shipped tuning of the default "
                   "scenario when --config is not given; 'none' for none)")
    p.add_argument("--reference", default=None, help="compare every policy with this spec instead")
    p.add_argument("--out", default=d.out, help=f"output folder (default {d.out})")
    p.add_argument("--no-plots", dest="plots", action="store_false")
    p.add_argument("--quiet", dest="progress", action="store_false", help="no progress bar")


def args_from_namespace(ns: argparse.Namespace) -> Args:
    values = {k: getattr(ns, k) for k in asdict(Args(policies=[])) if hasattr(ns, k)}
    if values.get("policies") is None:
        values["policies"] = default_policies()
    return Args(**values)


def main(args: Args) -> dict:
    if args.suite:
        from uwb_env.training.suite import format_suite, run_suite

        result = run_suite(list(args.policies), args.seeds, args.workers, args.out,
                           None if args.suite == "default" else args.suite, args.suite_scenarios or None,
                           plots=args.plots, show=args.progress)
        print(format_suite(result))
        if args.out:
            print(f"wrote {args.out}/ (suite_per_scenario.csv, suite_aggregate.csv, <scenario>/"
                  f"{', performance_profile.png' if args.plots else ''})")
        return result
    if args.scenarios:
        return evaluate_scenarios(args)
    results = evaluate(args)
    print(format_table(results["summary"]))
    print(describe_reference(results))
    if args.out:
        print(f"wrote {args.out}/ ({', '.join(os.path.basename(p) for p in results.get('written', []))})")
    return results


def _display_path(path: str) -> str:
    """Relative to the working directory when below it (no absolute paths in printed output)."""
    if Path(path).resolve() == DEFAULT_TUNED.resolve():
        return "the shipped training/tuned/default.json"
    try:
        return os.path.relpath(path) if not os.path.relpath(path).startswith("..") else path
    except ValueError:
        return path


def describe_reference(results: dict) -> str:
    lines = []
    if results.get("reference"):
        lines.append(f"reference: {results['reference']} ({results['reference_kind']}"
                     + (f", from {_display_path(results['tuned_file'])})" if results.get("tuned_file") else ")"))
    for spec, m in (results.get("matched_budget") or {}).items():
        rate = next(r["calibrations_per_min"] for r in results["summary"] if r["policy"] == spec)
        if not np.isfinite(m["fixed_iqm_at_matched_rate_m"]):
            lines.append(f"matched budget: {spec}'s {rate:.1f} cal/min lies outside the fixed-interval sweep "
                         "(no extrapolation)")
            continue
        lines.append(f"matched budget: the fixed-interval curve at {spec}'s {rate:.1f} cal/min has IQM "
                     f"{m['fixed_iqm_at_matched_rate_m']:.3f} m [{m['ci_low_m']:.3f}, {m['ci_high_m']:.3f}]")
    seeds = results["seeds"]
    lines.append(f"test seeds {seeds[0]}..{seeds[-1]} ({len(seeds)} per policy)")
    return "\n".join(lines)


def evaluate_scenarios(args: Args) -> dict:
    """Evaluate every scenario file; one folder each, and one CSV of all summary rows."""
    from dataclasses import replace
    from pathlib import Path

    by_scenario, rows = {}, []
    for path in args.scenarios:
        name = Path(path).stem
        out = os.path.join(args.out, name) if args.out else None
        # A learned model fits one env shape: scenarios that change it (e.g. 8 anchors) run without it.
        results = evaluate(replace(args, config=path, scenarios=[], out=out, skip_incompatible=True))
        print(f"\n== scenario {name} ({path})\n" + format_table(results["summary"]))
        by_scenario[name] = results
        rows += [{"scenario": name, **r} for r in results["summary"]]
    if args.out:
        with open(os.path.join(args.out, "scenarios.csv"), "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
        print(f"wrote {args.out}/<scenario>/ and {args.out}/scenarios.csv")
    return by_scenario


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_arguments(parser)
    main(args_from_namespace(parser.parse_args()))
