"""Distributed sweeps on Ray Tune: the harness's scheduler sweeps, or an SB3 hyperparameter search.

Usage::

    python -m uwb_env.training.sweep_tune harness --policies fixed:5 fixed:10 threshold:0.15 --seeds 8 --out runs/sweep
    python -m uwb_env.training.sweep_tune sb3 --grid learning_rate=1e-4,3e-4 --total-timesteps 50000 --out runs/sb3sweep
    ... --address auto     # on an existing cluster (default: a local Ray instance)

``harness``: one Tune trial per policy spec, each running the evaluation seeds; the driver
gathers the trials and writes exactly the files of ``training.evaluate`` (episodes.csv,
summary.csv/json, plots) into ``--out``. ``sb3``: one trial per grid point, each a
``training.train`` run in its own folder; ``sb3_sweep.json`` ranks them by the validation
EvalCallback's best mean reward.
"""

from __future__ import annotations

import argparse
import itertools
import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from uwb_env.training.hyperparams_io import parse_value


@dataclass
class Args:
    kind: str = "harness"
    policies: list[str] = field(default_factory=list)
    """harness: specs to evaluate (default: the fixed-interval and threshold sweeps)"""
    seeds: int = 6
    max_cycles: int = 500
    config: str | None = None
    grid: list[str] = field(default_factory=list)
    """sb3: ``key=v1,v2`` hyperparameter grids (their product is searched)"""
    total_timesteps: int = 50_000
    out: str = "runs/sweep"
    address: str | None = None
    cpus_per_trial: float = 1.0


def _harness_trial(config: dict) -> None:
    from ray import tune
    from uwb_env.training.evaluate import run_episode

    episodes = [run_episode(config["spec"], seed, config["env_config"]) for seed in config["seeds"]]
    for e in episodes:  # JSON-friendly traces
        e["tag_error_trace"] = e["tag_error_trace"].tolist()
        e["anchor_error_trace"] = e["anchor_error_trace"].tolist()
    tune.report({"mean_tag_error_m": float(np.mean([e["mean_tag_error_m"] for e in episodes])),
                 "episodes_json": json.dumps(episodes)})


def _sb3_trial(config: dict) -> None:
    from ray import tune
    from uwb_env.training import train

    hp = [f"{k}={v}" for k, v in config["hp"].items()]
    record = train.main(train.Args(total_timesteps=config["total_timesteps"], out=config["out"], hp=hp,
                                   env_config=config["env_config"],
                                   progress_bar=False, eval_freq=max(config["total_timesteps"] // 4, 1),
                                   checkpoint_freq=max(config["total_timesteps"] // 4, 1), tensorboard=False))
    tune.report({"best_eval_mean_reward": record.get("best_eval_mean_reward", float("nan")),
                 "training_wall_s": record["training_wall_s"], "out": config["out"]})


def main(args: Args) -> dict:
    import ray
    from ray import tune
    from uwb_env.training import evaluate

    from uwb_env.cli import load_overrides

    if args.kind not in ("harness", "sb3"):
        raise ValueError(f"kind={args.kind!r}: must be 'harness' or 'sb3'")
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    if not ray.is_initialized():
        ray.init(address=args.address, include_dashboard=False, log_to_driver=False)
    start = time.perf_counter()
    run_config = tune.RunConfig(storage_path=str(out / "tune"), name=args.kind, verbose=0)
    resources = {"cpu": args.cpus_per_trial}
    if args.kind == "harness":
        config = evaluate._env_config(load_overrides(args.config), args.max_cycles)
        specs = list(args.policies) or evaluate.sweep_specs()
        seeds = [evaluate.EVAL_SEED_BASE + i for i in range(args.seeds)]
        space = {"spec": tune.grid_search(specs), "seeds": seeds, "env_config": config.to_dict()}
        tuner = tune.Tuner(tune.with_resources(_harness_trial, resources), param_space=space, run_config=run_config)
        grid = tuner.fit()
        episodes = [e for r in grid for e in json.loads(r.metrics["episodes_json"])]
        for e in episodes:
            e["tag_error_trace"] = np.asarray(e["tag_error_trace"])
            e["anchor_error_trace"] = np.asarray(e["anchor_error_trace"])
        results = {"summary": evaluate.summarize(episodes, specs, main=specs), "episodes": episodes,
                   "seeds": seeds, "config": config.to_dict(), "dt_s": config.sim.dt_s}
        evaluate.write_outputs(results, str(out))
        record = {"kind": "harness", "trials": len(specs), "wall_s": time.perf_counter() - start,
                  "summary": results["summary"]}
    else:
        grids = {}
        for item in args.grid:
            key, sep, values = item.partition("=")
            if not sep:
                raise ValueError(f"grid={item!r}: expected key=v1,v2")
            grids[key] = [parse_value(v) for v in values.split(",")]
        points = [dict(zip(grids, combo, strict=True)) for combo in itertools.product(*grids.values())] or [{}]
        space = {"hp": tune.grid_search(points), "total_timesteps": args.total_timesteps,
                 "env_config": str(Path(args.config).resolve()) if args.config else None,
                 "out": tune.sample_from(lambda spec: str(out / "trials" / "_".join(
                     f"{k}={v}" for k, v in spec.config["hp"].items()) or "default"))}
        tuner = tune.Tuner(tune.with_resources(_sb3_trial, resources), param_space=space, run_config=run_config)
        grid = tuner.fit()
        failed = [f"{r.config['hp']}: {r.error}" for r in grid if r.error]
        if failed:
            raise RuntimeError("SB3 sweep trials failed: " + "; ".join(failed))
        trials = sorted(({"hp": r.config["hp"], **{k: r.metrics[k] for k in ("best_eval_mean_reward",
                          "training_wall_s", "out")}} for r in grid), key=lambda t: -t["best_eval_mean_reward"])
        record = {"kind": "sb3", "trials": trials, "wall_s": time.perf_counter() - start}
        (out / "sb3_sweep.json").write_text(json.dumps(record, indent=1, default=str))
    (out / "sweep.json").write_text(json.dumps({k: v for k, v in record.items() if k != "summary"}, indent=1,
                                               default=str))
    return record


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("kind", choices=("harness", "sb3"))
    d = Args()
    p.add_argument("--policies", nargs="*", default=[])
    p.add_argument("--seeds", type=int, default=d.seeds)
    p.add_argument("--max-cycles", type=int, default=d.max_cycles)
    p.add_argument("--config", default=None)
    p.add_argument("--grid", nargs="*", default=[])
    p.add_argument("--total-timesteps", type=int, default=d.total_timesteps)
    p.add_argument("--out", default=d.out)
    p.add_argument("--address", default=None)
    p.add_argument("--cpus-per-trial", type=float, default=d.cpus_per_trial)
    rec = main(Args(**vars(p.parse_args())))
    print(json.dumps({k: v for k, v in rec.items() if k != "summary"}, indent=1, default=str))
