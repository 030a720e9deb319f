"""Episode-level robustness of the localization pipeline (issue: localization that never passes a
wrong answer off as a success).

Two figures:

1. **Catastrophic episodes**: the share of episodes whose mean tag error exceeds 1 m, for fixed
   calibration intervals of 10-50 steps in the default scenario (and in the free-motion stress
   scenario), with a Wilson 95 % interval. ``--before REV`` measures the same on another
   revision of the code (checked out into a temporary git worktree, run in a subprocess of the
   same interpreter), side by side in the same run.
2. **Never raises**: ``reset()`` and ``step()`` over seeds whose team size (3-64 anchors), tag
   count (1-50) and dimension (2D/3D) are drawn per seed; every exception is counted by type.

    python benchmarks/bench_episodes.py                 # 500 episodes per interval, 1,000 seeds
    python benchmarks/bench_episodes.py --quick         # a smoke run
    python benchmarks/bench_episodes.py --before af25bf1
    python benchmarks/bench_episodes.py --only-never-raises   # the sweep alone, merged into the JSON

Writes ``benchmarks/results/bench_episodes.json`` (``_quick`` with --quick).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import write_results  # noqa: E402

INTERVALS = (10, 20, 30, 40, 50)
SEED_BASE = 3_000_000  # disjoint from training (0+), validation (500,000+) and test (1,000,000+)
FREE_MOTION = {"sim": {"anchor_motion": {"model": "heading"}, "tag_motion": {"model": "heading"}}}


def _episode(args) -> float:
    interval, seed, overrides = args
    from uwb_env.agents.baselines import FixedIntervalPolicy

    from uwb_env import parallel_env
    from uwb_env.env.policy import rollout

    return float(np.mean(rollout(parallel_env(**overrides), FixedIntervalPolicy(interval), seed=seed).tag_error_m))


def wilson(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    from scipy.stats import binomtest

    ci = binomtest(k, n).proportion_ci(confidence_level=0.95, method="wilson")
    return float(ci.low), float(ci.high)


def catastrophic(n: int, overrides: dict, workers: int) -> dict:
    out = {}
    with ProcessPoolExecutor(workers) as pool:
        for interval in INTERVALS:
            errs = np.array(list(pool.map(_episode, [(interval, SEED_BASE + s, overrides) for s in range(n)],
                                          chunksize=8)))
            k = int((errs > 1.0).sum())
            low, high = wilson(k, n)
            out[interval] = {"rate": k / n, "ci_low": low, "ci_high": high, "n": n,
                             "median_m": float(np.median(errs)), "mean_m": float(errs.mean())}
    return out


def _survive(seed: int) -> tuple[str, dict]:
    from uwb_env import parallel_env

    start = time.perf_counter()
    rng = np.random.default_rng(seed)
    dim = int(rng.choice([2, 3]))
    n = int(rng.choice([3, 4, 5, 8, 16, 32, 64])) if dim == 2 else int(rng.choice([4, 5, 8, 16, 32, 64]))
    m = int(rng.choice([1, 3, 10, 50]))
    case = {"n_anchors": n, "n_tags": m, "dim": dim}
    try:
        env = parallel_env(max_cycles=40, sim=case)
        env.reset(seed=seed)
        t = 0
        while env.agents:
            env.step({a: int(t % 10 == 0) for a in env.agents})
            t += 1
    except Exception as err:  # counted by type: the figure is that there are none
        return f"{type(err).__name__}: {str(err)[:120]}", {**case, "seconds": time.perf_counter() - start}
    return "", {**case, "seconds": time.perf_counter() - start}


def never_raises(n_seeds: int, workers: int) -> dict:
    with ProcessPoolExecutor(workers) as pool:
        outcomes = list(pool.map(_survive, range(n_seeds), chunksize=4))
    errors = Counter(msg.split(":")[0] for msg, _ in outcomes if msg)
    examples = [{"error": msg, **case} for msg, case in outcomes if msg][:5]
    slowest = max(outcomes, key=lambda o: o[1]["seconds"])[1]
    return {"seeds": n_seeds, "exceptions": sum(errors.values()), "by_type": dict(errors), "examples": examples,
            "slowest": slowest}


def code_version() -> str:
    root = Path(__file__).resolve().parents[1]
    out = subprocess.run(["git", "-C", str(root), "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    return out.stdout.strip() or "unknown"


def sweep_keys(sweep: dict, seeds: int, version: str) -> dict:
    """The never-raises sweep's figures as flat JSON keys."""
    return {"never_raises_seeds": seeds, "never_raises_exceptions": sweep["exceptions"],
            "never_raises_by_type": json.dumps(sweep["by_type"]),
            "never_raises_examples": json.dumps(sweep["examples"]),
            "never_raises_slowest_episode": json.dumps(sweep["slowest"]), "never_raises_code_version": version}


def only_never_raises(seeds: int, workers: int) -> None:
    """Re-run the sweep alone and update its keys in the committed JSON (the catastrophic
    figures keep the revision they were measured on, ``code_version``)."""
    t0, version = time.perf_counter(), code_version()  # the code the workers import
    sweep = never_raises(seeds, workers)
    path = Path(__file__).resolve().parent / "results" / "bench_episodes.json"
    results = json.loads(path.read_text()) if path.exists() else {}
    for key in ("date", "machine", "quick", "never_raises_status"):
        results.pop(key, None)
    results.update(sweep_keys(sweep, seeds, version), never_raises_wall_s=round(time.perf_counter() - t0, 1))
    print(f"never raises: {sweep['exceptions']} exceptions over {seeds} seeds {sweep['by_type'] or ''}; "
          f"slowest episode {sweep['slowest']}")
    write_results("bench_episodes", results, False)


def before(rev: str, n: int, workers: int) -> dict:
    """The catastrophic figure on another revision: a temporary worktree, same interpreter."""
    root = Path(__file__).resolve().parents[1]
    with tempfile.TemporaryDirectory() as tmp:
        tree = Path(tmp) / "tree"
        subprocess.run(["git", "-C", str(root), "worktree", "add", "--detach", str(tree), rev], check=True,
                       capture_output=True)
        try:
            here = str(Path(__file__).parent)
            code = (f"import json,sys; sys.path.insert(0, {here!r}); import bench_episodes as b; "
                    f"print(json.dumps(b.catastrophic({n}, {{}}, {workers})))")
            env = dict(os.environ, PYTHONPATH=str(tree))
            out = subprocess.run([sys.executable, "-c", code], env=env, check=True, capture_output=True, text=True,
                                 cwd=tree)
            return {int(k): v for k, v in json.loads(out.stdout.strip().splitlines()[-1]).items()}
        finally:
            subprocess.run(["git", "-C", str(root), "worktree", "remove", "--force", str(tree)], capture_output=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--episodes", type=int, default=None, help="episodes per interval (default 500; quick 40)")
    parser.add_argument("--seeds", type=int, default=None, help="seeds of the never-raises sweep (1000; quick 40)")
    parser.add_argument("--before", default=None, help="git revision to measure side by side (e.g. af25bf1)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--only-never-raises", action="store_true",
                        help="run the never-raises sweep alone; update its keys in the committed JSON")
    parser.add_argument("--skip-never-raises", action="store_true",
                        help="catastrophic figures only; the sweep's (and, without --before, the before-run's) "
                             "keys are kept from the committed JSON with their own code versions")
    args = parser.parse_args()
    if args.only_never_raises:
        only_never_raises(args.seeds or 1000, args.workers)
        return
    n = args.episodes or (40 if args.quick else 500)
    seeds = args.seeds or (40 if args.quick else 1000)
    t0, version = time.perf_counter(), code_version()
    default = catastrophic(n, {}, args.workers)
    free = catastrophic(max(n // 5, 20), FREE_MOTION, args.workers)
    old = before(args.before, max(n // 2, 20), args.workers) if args.before else None
    results = {
        "catastrophic_episode_rate": max(v["rate"] for v in default.values()),
        "catastrophic_episodes_per_interval": n,
        "code_version": version,
    }
    if args.skip_never_raises:
        path = Path(__file__).resolve().parent / "results" / "bench_episodes.json"
        kept = json.loads(path.read_text()) if path.exists() and not args.quick else {}
        results.update({k: v for k, v in kept.items() if k.startswith("never_raises")
                        or (old is None and k.startswith("before"))})
        if old is None:
            results.update({k: v for k, v in kept.items() if k.endswith("_before")})
            if "before_revision" in kept:
                results["before_code_version_note"] = "before-figures kept from the run at " + str(
                    kept.get("code_version"))
    else:
        sweep = never_raises(seeds, args.workers)
        results.update(sweep_keys(sweep, seeds, version))
    print(f"{'interval':>8} {'default rate':>13} {'95% CI':>15} {'median m':>9} {'free-motion rate':>17}"
          + (f" {'before (' + args.before + ')':>16}" if old else ""))
    for k in INTERVALS:
        d, f = default[k], free[k]
        results[f"catastrophic_episode_rate_fixed{k}"] = d["rate"]
        results[f"catastrophic_episode_rate_fixed{k}_ci_high"] = d["ci_high"]
        results[f"median_tag_error_m_fixed{k}"] = d["median_m"]
        results[f"free_motion_catastrophic_rate_fixed{k}"] = f["rate"]
        line = (f"{k:>8} {d['rate']:>13.4f} {d['ci_low']:>7.4f}-{d['ci_high']:<7.4f} {d['median_m']:>9.3f}"
                f" {f['rate']:>17.4f}")
        if old:
            results[f"catastrophic_episode_rate_fixed{k}_before"] = old[k]["rate"]
            line += f" {old[k]['rate']:>16.4f}"
        print(line)
    results["free_motion_episodes_per_interval"] = max(n // 5, 20)
    if old:
        results["before_revision"] = args.before
        results["before_episodes_per_interval"] = max(n // 2, 20)
    if not args.skip_never_raises:
        print(f"never raises: {sweep['exceptions']} exceptions over {seeds} seeds {sweep['by_type'] or ''}")
    results["wall_s"] = round(time.perf_counter() - t0, 1)
    write_results("bench_episodes_quick" if args.quick else "bench_episodes", results, args.quick)


if __name__ == "__main__":
    main()
