"""Does a learned scheduler beat the fixed-interval trade-off curve?

Trains PPO on the centralized scheduler env (default dynamic scenario) within a wall-clock
budget on this machine, then evaluates it on held-out seeds beside the fixed-interval sweep,
the threshold heuristics and the (ground-truth) oracle. The fixed-interval curve is
interpolated at the learned policy's calibration rate (error at matched rate), and inverted
at its error (rate needed by a fixed interval to match it). Also measures DummyVecEnv vs
SubprocVecEnv throughput.

Writes benchmarks/results/bench_scheduling.json and the evaluation into ``--out`` and ships
the model in agents/models/ when it is under 5 MB. ``--quick`` ends within a minute.

Its comparison (24 seeds, means, an untuned curve) is a training check, not a verdict: whether
a learned scheduler beats the tuned heuristics is measured by ``bench_protocol.py`` (the
evaluation protocol: >= 100 test seeds, IQM with bootstrap CIs, paired differences, tuned
baselines), whose results are in docs/results/scheduling/.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._common import print_table, write_results  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
MODEL_DIR = ROOT / "agents" / "models"  # shipped: agents/models/ppo_scheduler/model.zip


def vec_env_throughput(kind: str, steps: int) -> float:
    """Env steps/s of the training VecEnv alone (8 copies; the batched mode with 32)."""
    from uwb_env.training.train import make_vec_env

    venv = make_vec_env("batched", 32, {}, 0) if kind == "batched" else make_vec_env("scheduler", 8, {}, 0, kind)
    venv.reset()
    n = steps // venv.num_envs
    start = time.perf_counter()
    for _ in range(n):
        venv.step(np.zeros(venv.num_envs, dtype=np.int64))
    rate = n * venv.num_envs / (time.perf_counter() - start)
    venv.close()
    return rate


def fixed_curve(summary: list[dict]) -> tuple[np.ndarray, np.ndarray]:
    pts = sorted((r["calibrations_per_min"], r["mean_tag_error_m"]) for r in summary
                 if r["policy"].startswith("fixed:"))
    rate, err = np.array(pts).T
    return rate, err


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--budget-s", type=float, default=720.0, help="training wall-clock budget")
    p.add_argument("--seeds", type=int, default=24, help="evaluation episodes per policy")
    p.add_argument("--out", default=str(ROOT / "runs" / "bench_scheduling"))
    p.add_argument("--mode", choices=("dummy", "subproc", "batched", "fastest"), default="dummy",
                   help="training env mode (default: the scheduler env on DummyVecEnv)")
    a = p.parse_args()
    budget, seeds = (15.0, 2) if a.quick else (a.budget_s, a.seeds)

    from uwb_env.training import evaluate, train

    dummy = vec_env_throughput("dummy", 2000 if a.quick else 16000)
    subproc = vec_env_throughput("subproc", 2000 if a.quick else 16000)
    batched = vec_env_throughput("batched", 4000 if a.quick else 64000)
    out = Path(a.out)
    if out.exists():
        shutil.rmtree(out)
    # The committed result trained the scheduler env on DummyVecEnv (--mode dummy, the default);
    # --mode fastest picks the fastest of the three (same observations and reward).
    modes = {"dummy": (("scheduler", "dummy"), dummy), "subproc": (("scheduler", "subproc"), subproc),
             "batched": (("batched", "dummy"), batched)}
    fastest = (max(modes.values(), key=lambda item: item[1]) if a.mode == "fastest" else modes[a.mode])[0]
    targs = train.Args(algo="ppo", env=fastest[0], total_timesteps=10_000_000, seed=0, out=str(out),
                       vec_env=fastest[1], checkpoint_freq=50_000, eval_freq=50_000, eval_episodes=4,
                       progress_bar=True, max_wall_s=budget)
    record = train.main(targs)
    # Model selection on the validation seeds (never the evaluation seeds): the EvalCallback's
    # best checkpoint when it beat the final model there.
    best = out / "best" / "best_model.zip"
    use_best = best.exists() and record.get("best_eval_mean_reward", -1e18) > record.get("last_eval_mean_reward",
                                                                                          -1e18)
    model = best if use_best else out / "model.zip"

    eargs = evaluate.Args(policies=[f"learned:{model}", "fixed:10", "threshold:0.15", "residual:0.2", "oracle:0.3"],
                          seeds=seeds, max_cycles=500, sweep=True, workers=2,
                          out=str(out / "eval"),
                          progress=True)
    results = evaluate.main(eargs)
    rows = {r["policy"]: r for r in results["summary"]}
    learned = rows[f"learned:{model}"]
    rate, err = fixed_curve(results["summary"])
    fixed_at_rate = float(np.interp(learned["calibrations_per_min"], rate, err))
    # The lowest rate at which the fixed-interval curve reaches the learned error (if any).
    reach = rate[err <= learned["mean_tag_error_m"]]
    fixed_rate_for_error = float(reach.min()) if len(reach) else float("nan")
    error_gain = 1 - learned["mean_tag_error_m"] / fixed_at_rate
    rate_saving = 1 - learned["calibrations_per_min"] / fixed_rate_for_error if len(reach) else float("nan")
    met = bool(error_gain >= 0.20 or (np.isfinite(rate_saving) and rate_saving >= 0.30))

    print_table("Learned scheduler vs the fixed-interval curve (held-out seeds)",
                ["quantity", "value"],
                [["learned mean tag error (m)", learned["mean_tag_error_m"]],
                 ["fixed-interval error at the same rate (m)", fixed_at_rate],
                 ["error ratio learned / fixed", learned["mean_tag_error_m"] / fixed_at_rate],
                 ["learned calibrations / min", learned["calibrations_per_min"]],
                 ["fixed-interval rate for the same error (/min)", fixed_rate_for_error],
                 ["training wall (s)", record["training_wall_s"]],
                 ["training env steps", record["num_timesteps"]],
                 ["DummyVecEnv steps/s (8 envs)", dummy], ["SubprocVecEnv steps/s (8 envs)", subproc],
                 ["batched VecEnv steps/s (32 copies)", batched], ["trained on", "/".join(fastest)],
                 ["target met (>=20% lower error or >=30% fewer calibrations)", str(met)]])
    figures = {
        "learned_mean_tag_error_m": learned["mean_tag_error_m"],
        "fixed_interval_mean_tag_error_m": fixed_at_rate,
        "learned_to_fixed_error_ratio": learned["mean_tag_error_m"] / fixed_at_rate,
        "learned_calibrations_per_min": learned["calibrations_per_min"],
        "fixed_interval_calibrations_per_min_for_same_error": fixed_rate_for_error,
        "calibration_saving_vs_fixed": rate_saving,
        "threshold_mean_tag_error_m": rows["threshold:0.15"]["mean_tag_error_m"],
        "threshold_calibrations_per_min": rows["threshold:0.15"]["calibrations_per_min"],
        "residual_mean_tag_error_m": rows["residual:0.2"]["mean_tag_error_m"],
        "residual_calibrations_per_min": rows["residual:0.2"]["calibrations_per_min"],
        "oracle_mean_tag_error_m": rows["oracle:0.3"]["mean_tag_error_m"],
        "oracle_calibrations_per_min": rows["oracle:0.3"]["calibrations_per_min"],
        "paper_fixed_10_mean_tag_error_m": rows["fixed:10"]["mean_tag_error_m"],
        "training_wall_s": record["training_wall_s"],
        "model_selected": "best_on_validation" if use_best else "final",
        "training_env_steps": record["num_timesteps"],
        "dummy_vec_env_steps_per_s": dummy,
        "subproc_vec_env_steps_per_s": subproc,
        "batched_vec_env_steps_per_s": batched,
        "training_env_mode": "/".join(fastest),
        "eval_seeds": seeds,
        "target_met": met,
    }
    figures = {k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in figures.items()}
    if not a.quick:
        write_results("bench_scheduling", figures, quick=False)
        files = {"model.zip": model, "vecnormalize.pkl": model.with_name("vecnormalize.pkl"),
                 "run.json": model.with_name("run.json")}
        if sum(f.stat().st_size for f in files.values()) < 5_000_000:
            (MODEL_DIR / "ppo_scheduler").mkdir(parents=True, exist_ok=True)
            for name, src in files.items():
                shutil.copy(src, MODEL_DIR / "ppo_scheduler" / name)
    else:
        write_results("bench_scheduling_quick", figures, quick=True)


if __name__ == "__main__":
    main()
