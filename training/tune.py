"""Tune every heuristic family on validation seeds for the env's return (``uwb-env tune``).

Each family (fixed interval, uncertainty threshold, residual trigger, the per-anchor thresholds on
the predicted std and on the drift since calibration) has one parameter. The
tuner evaluates a grid on the same validation seeds (common random numbers: every candidate
sees the same episodes), then refines around the best point by bisection towards its better
neighbour, and keeps the candidate with the highest mean return. The result file names the
tuned spec of each family and the best of them; ``uwb-env evaluate --tuned FILE`` adds them
to the comparison and names the best tuned heuristic in its verdicts.

Seeds: validation seeds ``VALIDATION_SEED_BASE + i`` (the block training uses to pick
checkpoints), disjoint from the evaluation's test seeds (``evaluate.EVAL_SEED_BASE``).
"""

from __future__ import annotations

import argparse
import json
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

VALIDATION_SEED_BASE = 500_000

# family -> (grid, integer parameter?, (lowest, highest) allowed)
FAMILIES: dict[str, tuple[tuple[float, ...], bool, tuple[float, float]]] = {
    "fixed": ((5, 8, 12, 18, 27, 40, 60, 90, 135, 200, 300), True, (1, 1000)),
    "threshold": ((0.05, 0.08, 0.12, 0.17, 0.25, 0.35, 0.5, 0.7, 1.0), False, (0.01, 5.0)),
    "residual": ((0.05, 0.08, 0.12, 0.17, 0.25, 0.35, 0.5, 0.7, 1.0), False, (0.01, 5.0)),
    # per-anchor rounds ("re-locate me") and team rounds: the heuristic for the per-anchor actions
    "per_anchor_threshold": ((0.05, 0.08, 0.12, 0.17, 0.25, 0.35, 0.5, 0.7, 1.0), False, (0.01, 5.0)),
    # the same on the drift since the anchor's last calibration (agents/per_anchor.py)
    "per_anchor_drift": ((0.05, 0.08, 0.12, 0.17, 0.25, 0.35, 0.5, 0.7, 1.0), False, (0.01, 5.0)),
}


def spec_of(family: str, value: float) -> str:
    integer = FAMILIES[family][1] if family in FAMILIES else False
    return f"{family}:{int(value)}" if integer else f"{family}:{float(value):.4g}"


@dataclass(frozen=True)
class FamilyResult:
    family: str
    best_spec: str
    best_value: float
    best_return: float
    best_return_sem: float
    evaluated: dict[float, float] = field(default_factory=dict)
    """parameter -> mean return of every candidate tried"""


def tune_family(family: str, objective: Callable[[Sequence[float]], Sequence[float]],
                grid: Sequence[float] | None = None, integer: bool | None = None, refine_rounds: int = 3,
                sem: Callable[[float], float] | None = None) -> FamilyResult:
    """Maximize ``objective`` (a batch of parameters -> their mean returns) over one family.

    Grid first, then ``refine_rounds`` rounds of bisection between the best point and each
    neighbour (integers stop when no new integer lies between).
    """
    default_grid, default_integer, _ = FAMILIES.get(family, ((), False, (0, 0)))
    grid = sorted(set(grid if grid is not None else default_grid))
    integer = default_integer if integer is None else integer
    if len(grid) < 2:
        raise ValueError(f"grid={grid!r}: needs at least 2 points")
    scores: dict[float, float] = {}

    def run(points):
        points = [p for p in dict.fromkeys(points) if p not in scores]
        if points:
            scores.update(zip(points, map(float, objective(points)), strict=True))

    run(grid)
    for _ in range(refine_rounds):
        xs = sorted(scores)
        i = int(np.argmax([scores[x] for x in xs]))
        new = []
        for j in (i - 1, i + 1):
            if 0 <= j < len(xs):
                mid = 0.5 * (xs[i] + xs[j])
                mid = round(mid) if integer else mid
                if mid not in scores and mid != xs[i] and mid != xs[j]:
                    new.append(mid)
        if not new:
            break
        run(new)
    best = max(scores, key=scores.get)
    return FamilyResult(family, spec_of(family, best), float(best), scores[best],
                        float(sem(best)) if sem else float("nan"), dict(sorted(scores.items())))


@dataclass
class Args:
    families: list[str] = field(default_factory=lambda: list(FAMILIES))
    seeds: int = 24
    """validation episodes per candidate"""
    seed_offset: int = 0
    max_cycles: int = 500
    config: str | None = None
    workers: int = 1
    out: str = "runs/tune/tuned.json"
    refine_rounds: int = 2
    progress: bool = True


def tune(args: Args) -> dict:
    """Tune every family of ``args.families`` on the env of ``args.config``; write ``args.out``."""
    from uwb_env.training.evaluate import _env_config, run_jobs

    from uwb_env.cli import load_overrides

    unknown = [f for f in args.families if f not in FAMILIES]
    if unknown:
        raise ValueError(f"families={unknown!r}: known families are {', '.join(FAMILIES)}")
    if args.seeds < 2:
        raise ValueError(f"seeds={args.seeds!r}: must be >= 2")
    config_dict = _env_config(load_overrides(args.config), args.max_cycles).to_dict()
    seeds = [VALIDATION_SEED_BASE + args.seed_offset + i for i in range(args.seeds)]
    returns: dict[str, np.ndarray] = {}

    def objective_for(family):
        def objective(points):
            specs = [spec_of(family, p) for p in points]
            jobs = [(s, seed, config_dict) for s in specs for seed in seeds]
            episodes = run_jobs(jobs, args.workers, f"tune {family} ({len(specs)} candidates)", args.progress)
            for s in specs:
                returns[s] = np.array([e["return"] for e in episodes if e["policy"] == s])
            return [returns[s].mean() for s in specs]
        return objective

    def sem_for(family):
        return lambda v: returns[spec_of(family, v)].std(ddof=1) / np.sqrt(len(seeds))

    results = {f: tune_family(f, objective_for(f), refine_rounds=args.refine_rounds, sem=sem_for(f))
               for f in args.families}
    best = max(results.values(), key=lambda r: r.best_return)
    record = {
        "objective": "mean env return over validation seeds (higher is better)",
        "best_tuned_heuristic": best.best_spec,
        "tuned": {f: r.best_spec for f, r in results.items()},
        "families": {f: {"best_spec": r.best_spec, "best_return": r.best_return, "best_return_sem": r.best_return_sem,
                         "evaluated": {spec_of(f, k): v for k, v in r.evaluated.items()}}
                     for f, r in results.items()},
        "validation_seeds": [seeds[0], seeds[-1]],
        "config": config_dict,
        "scenario": args.config,
    }
    if args.out:
        os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
        with open(args.out, "w") as f:
            json.dump(record, f, indent=2)
    return record


def load_tuned(path: str) -> dict:
    """The record written by :func:`tune` (``tuned``: family -> spec; ``best_tuned_heuristic``)."""
    with open(path) as f:
        record = json.load(f)
    if "tuned" not in record or "best_tuned_heuristic" not in record:
        raise ValueError(f"--tuned {path}: not a tuning result (no 'tuned'/'best_tuned_heuristic' keys)")
    return record


def add_arguments(p: argparse.ArgumentParser) -> None:
    d = Args()
    p.add_argument("--families", nargs="+", default=d.families, help=f"heuristic families ({', '.join(FAMILIES)})")
    p.add_argument("--seeds", type=int, default=d.seeds, help=f"validation episodes per candidate (default {d.seeds})")
    p.add_argument("--seed-offset", type=int, default=d.seed_offset)
    p.add_argument("--max-cycles", type=int, default=d.max_cycles)
    p.add_argument("--config", default=None, help="YAML/JSON file with EnvConfig overrides (the scenario)")
    p.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1))
    p.add_argument("--refine-rounds", type=int, default=d.refine_rounds)
    p.add_argument("--out", default=d.out, help=f"result file (default {d.out})")
    p.add_argument("--quiet", dest="progress", action="store_false")


def main(args: Args) -> dict:
    record = tune(args)
    for family, info in record["families"].items():
        print(f"{family:10s} best {info['best_spec']:16s} return {info['best_return']:9.2f} "
              f"+- {info['best_return_sem']:.2f}  ({len(info['evaluated'])} candidates)")
    print(f"best tuned heuristic: {record['best_tuned_heuristic']}")
    if args.out:
        print(f"wrote {args.out}  (use: uwb-env evaluate --tuned {args.out})")
    return record


def args_from_namespace(ns: argparse.Namespace) -> Args:
    return Args(families=ns.families, seeds=ns.seeds, seed_offset=ns.seed_offset, max_cycles=ns.max_cycles,
                config=ns.config, workers=ns.workers, out=ns.out, refine_rounds=ns.refine_rounds, progress=ns.progress)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_arguments(parser)
    main(args_from_namespace(parser.parse_args()))
