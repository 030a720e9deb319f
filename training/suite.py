"""The scenario suite (``uwb-env evaluate --suite``): every scenario of
``training/scenarios/suite/suite.yml`` on its test seeds, in parallel, with the protocol's
statistics per scenario, an aggregate table and a performance profile.

Per scenario the reference is the best heuristic run there by env return (the suite does not
tune per scenario; tune one with ``uwb-env tune --config`` and evaluate it alone for a tuned
reference). A learned policy that does not fit a scenario's observations is left out of it.
"""

from __future__ import annotations

import csv
import os
import sys
import time
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np

SUITE_FILE = Path(__file__).with_name("scenarios") / "suite" / "suite.yml"


def load_suite(path: str | None = None) -> dict[str, dict]:
    """Scenario name -> {config, max_cycles, seeds: {training, validation, test}, description}."""
    import yaml

    path = path or str(SUITE_FILE)
    with open(path) as f:
        data = yaml.safe_load(f) or {}
    if not isinstance(data.get("scenarios"), dict) or not data["scenarios"]:
        raise ValueError(f"suite {path}: needs a non-empty 'scenarios' mapping")
    default_seeds = data.get("seeds", {})
    suite = {}
    for name, entry in data["scenarios"].items():
        seeds = {**default_seeds, **entry.get("seeds", {})}
        for split in ("training", "validation", "test"):
            if split not in seeds or len(seeds[split]) != 2 or seeds[split][0] > seeds[split][1]:
                raise ValueError(f"suite {path}: scenario {name!r}: seeds.{split}={seeds.get(split)!r}: "
                                 "need [first, last]")
        ranges = sorted(tuple(seeds[s]) for s in ("training", "validation", "test"))
        if any(a[1] >= b[0] for a, b in zip(ranges, ranges[1:], strict=False)):
            raise ValueError(f"suite {path}: scenario {name!r}: seed ranges overlap: {seeds}")
        suite[name] = {"config": entry.get("config") or {}, "max_cycles": int(entry.get("max_cycles", 500)),
                       "seeds": seeds, "description": entry.get("description", ""),
                       "held_out": bool(entry.get("held_out", False))}
    return suite


def progress_eta(items: Iterable, total: int, label: str, enabled: bool = True) -> Iterator:
    """Yield ``items`` while drawing ``label [####----] k/total elapsed ETA`` on stderr."""
    if not enabled:
        yield from items
        return
    start = last = time.perf_counter()
    for done, item in enumerate(items, 1):
        yield item
        now = time.perf_counter()
        if now - last > 0.5 or done == total:
            last = now
            elapsed = now - start
            eta = elapsed / done * (total - done)
            bar = "#" * int(30 * done / total)
            sys.stderr.write(f"\r{label} [{bar:<30}] {done}/{total}  {elapsed:6.0f}s  ETA {eta:5.0f}s")
            sys.stderr.flush()
    sys.stderr.write("\n")


def run_suite(policies: list[str], n_seeds: int, workers: int, out: str | None, suite_path: str | None = None,
              scenarios: list[str] | None = None, plots: bool = True, show: bool = True) -> dict:
    """Evaluate ``policies`` on ``n_seeds`` test seeds of every scenario; write the tables."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    from uwb_env.agents.registry import make_policy
    from uwb_env.training.evaluate import _env_config, _run_star, run_episode, summarize
    from uwb_env.training.protocol import best_heuristic

    suite = load_suite(suite_path)
    if scenarios:
        unknown = [s for s in scenarios if s not in suite]
        if unknown:
            raise ValueError(f"scenarios={unknown!r}: not in the suite ({', '.join(suite)})")
        suite = {k: v for k, v in suite.items() if k in scenarios}
    jobs, plan = [], {}
    for name, sc in suite.items():
        config = _env_config(sc["config"], sc["max_cycles"])
        first, last = sc["seeds"]["test"]
        if n_seeds > last - first + 1:
            raise ValueError(f"seeds={n_seeds}: scenario {name!r} has only {last - first + 1} test seeds")
        specs = []
        for spec in policies:
            problem = getattr(make_policy(spec, config.sim.dt_s), "incompatibility", lambda _: None)(config)
            if problem is None:
                specs.append(spec)
            elif show:
                print(f"{name}: skipping {spec}: {problem}")
        seeds = list(range(first, first + n_seeds))
        plan[name] = (specs, seeds, config)
        jobs += [(spec, seed, config.to_dict()) for spec in specs for seed in seeds]
    owners = [name for name, (specs, seeds, _) in plan.items() for _ in range(len(specs) * len(seeds))]
    if workers == 1:
        episodes = [run_episode(*j) for j in progress_eta(jobs, len(jobs), "suite", show)]
    else:
        context = multiprocessing.get_context("forkserver")
        with ProcessPoolExecutor(max_workers=workers, mp_context=context) as pool:
            episodes = list(progress_eta(pool.map(_run_star, jobs, chunksize=1), len(jobs), "suite", show))
    per_scenario, rows = {}, []
    for name, (specs, seeds, config) in plan.items():
        mine = [e for e, owner in zip(episodes, owners, strict=True) if owner == name]
        reference = best_heuristic(summarize(mine, specs, specs, statistics=False), specs)
        summary = summarize(mine, specs, specs, reference=reference if len(seeds) > 1 else None)
        per_scenario[name] = {"summary": summary, "episodes": mine, "seeds": seeds, "reference": reference,
                              "config": config.to_dict(), "dt_s": config.sim.dt_s}
        rows += [{"scenario": name, **{k: v for k, v in r.items() if k != "group"}} for r in summary]
    aggregate = aggregate_rows(per_scenario, policies)
    result = {"per_scenario": per_scenario, "rows": rows, "aggregate": aggregate}
    if out:
        result["written"] = write_suite(result, out, plots)
    return result


def aggregate_rows(per_scenario: dict, policies: list[str]) -> list[dict]:
    """Per policy over scenarios: scenarios run, mean of the per-scenario IQMs, how often it is
    the best by IQM, and how often significantly better / worse than the scenario's reference."""
    out = []
    for spec in policies:
        rows = [next((r for r in sc["summary"] if r["policy"] == spec), None) for sc in per_scenario.values()]
        bests = [min(sc["summary"], key=lambda r: r["iqm_tag_error_m"])["policy"] for sc in per_scenario.values()]
        present = [r for r in rows if r is not None]
        if not present:
            continue
        better = sum(1 for r in present if r.get("significant_vs_reference") and r["iqm_diff_vs_reference_m"] < 0)
        worse = sum(1 for r in present if r.get("significant_vs_reference") and r["iqm_diff_vs_reference_m"] > 0)
        out.append({"policy": spec, "uses_ground_truth": present[0]["uses_ground_truth"], "scenarios": len(present),
                    "mean_scenario_iqm_tag_error_m": float(np.mean([r["iqm_tag_error_m"] for r in present])),
                    "mean_catastrophic_rate": float(np.mean([r["catastrophic_rate"] for r in present])),
                    "best_iqm_in_scenarios": sum(b == spec for b in bests),
                    "significantly_better_than_reference": better, "significantly_worse_than_reference": worse})
    return out


def _write_csv(path: str, rows: list[dict]) -> str:
    keys = list(dict.fromkeys(k for r in rows for k in r))
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)
    return path


def write_suite(result: dict, out: str, plots: bool = True) -> list[str]:
    from uwb_env.training.evaluate import write_outputs

    os.makedirs(out, exist_ok=True)
    written = []
    for name, res in result["per_scenario"].items():
        written += write_outputs(res, os.path.join(out, name), plots=False)
    written.append(_write_csv(os.path.join(out, "suite_per_scenario.csv"), result["rows"]))
    written.append(_write_csv(os.path.join(out, "suite_aggregate.csv"), result["aggregate"]))
    if plots:
        from uwb_env.training.plots_protocol import performance_profile

        path = performance_profile(result["per_scenario"], os.path.join(out, "performance_profile.png"))
        if path:
            written.append(path)
    return written


def format_suite(result: dict) -> str:
    from uwb_env.training.protocol import format_comparison

    parts = []
    for name, res in result["per_scenario"].items():
        table = format_comparison(res["summary"]).split("\n\n")[0]  # the legend once, at the end
        parts.append(f"== {name} (test seeds {res['seeds'][0]}..{res['seeds'][-1]}; reference: best heuristic "
                     f"run, {res['reference']})\n{table}")
    head = ["policy", "scenarios", "mean IQM (m)", "mean catastr.", "best in", "signif. better", "signif. worse"]
    cells = [head] + [[r["policy"] + (" (GT)" if r["uses_ground_truth"] else ""), str(r["scenarios"]),
                       f"{r['mean_scenario_iqm_tag_error_m']:.3f}", f"{r['mean_catastrophic_rate']:.1%}",
                       str(r["best_iqm_in_scenarios"]), str(r["significantly_better_than_reference"]),
                       str(r["significantly_worse_than_reference"])] for r in result["aggregate"]]
    widths = [max(len(c[i]) for c in cells) for i in range(len(head))]
    lines = ["  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(row, widths, strict=True)))
             for row in cells]
    lines.insert(1, "-" * len(lines[0]))
    legend = format_comparison(next(iter(result["per_scenario"].values()))["summary"]).split("\n\n", 1)[1]
    return "\n\n".join(parts + ["== aggregate over scenarios\n" + "\n".join(lines),
                                "signif. better/worse: scenarios where the paired IQM difference to that "
                                "scenario's reference excludes 0\n" + legend])
