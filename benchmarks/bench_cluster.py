"""Ray: environment steps per second sampled by RLlib with 1 and 2 env runners, and the wall
time of a two-trial Tune sweep of the evaluation harness (needs the ``cluster`` extra).

The env steps/s are from RLlib's own counters over the timed training iterations (sampling
plus PPO updates, as a user sees them); a direct, un-trained rollout of the same env through
the policy hook runs beside them as the reference (ratio = RLlib / direct).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._common import print_table, write_results  # noqa: E402


def direct_env_steps_per_s(steps: int) -> float:
    from uwb_env.agents.baselines import NeverPolicy

    import uwb_env
    from uwb_env.env.policy import rollout

    env = uwb_env.parallel_env(max_cycles=steps)
    start = time.perf_counter()
    rollout(env, NeverPolicy(), seed=0)
    return steps / (time.perf_counter() - start)


def rllib_steps_per_s(runners: int, iterations: int, batch: int, tmp: str) -> float:
    from uwb_env.training.train_rllib import Args, main

    # iteration 1 includes start-up; time the rest
    main(Args(iterations=1, out=f"{tmp}/r{runners}", num_env_runners=runners, resume=False,
              hp=[f"train_batch_size_per_learner={batch}", "minibatch_size=250", "num_epochs=1"]))
    rec = main(Args(iterations=1 + iterations, out=f"{tmp}/r{runners}", num_env_runners=runners, resume=True,
                    hp=[f"train_batch_size_per_learner={batch}", "minibatch_size=250", "num_epochs=1"]))
    return rec["env_steps_per_s"]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true")
    a = p.parse_args()
    import ray
    from uwb_env.training.sweep_tune import Args as SweepArgs
    from uwb_env.training.sweep_tune import main as sweep

    iterations, batch = (1, 1000) if a.quick else (3, 4000)
    ray.init(num_cpus=3, include_dashboard=False, log_to_driver=False)
    with tempfile.TemporaryDirectory() as tmp:
        one = rllib_steps_per_s(1, iterations, batch, tmp)
        two = rllib_steps_per_s(2, iterations, batch, tmp)
        start = time.perf_counter()
        sweep(SweepArgs(kind="harness", policies=["fixed:10", "threshold:0.15"], seeds=2, max_cycles=100,
                        out=f"{tmp}/sweep"))
        sweep_wall = time.perf_counter() - start
    ray.shutdown()
    direct = direct_env_steps_per_s(2000)
    print_table("RLlib sampling (PPO iterations, 4 anchors / 3 tags)", ["what", "env steps/s", "vs direct"],
                [["RLlib, 1 env runner", one, one / direct], ["RLlib, 2 env runners", two, two / direct],
                 ["direct rollout (reference)", direct, 1.0]])
    print_table("Tune", ["what", "seconds"], [["two-trial harness sweep (2 seeds x 100 steps)", sweep_wall]])
    write_results("bench_cluster" + ("_quick" if a.quick else ""),
                  {"rllib_steps_per_s_1_runner": one, "rllib_steps_per_s_2_runners": two,
                   "direct_env_steps_per_s": direct, "two_trial_sweep_wall_s": sweep_wall,
                   "iterations_timed": iterations, "train_batch_size": batch}, a.quick)


if __name__ == "__main__":
    main()
