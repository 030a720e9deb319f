"""Throughput of the batched mode beside VMAS and MPE, in one run (issue: one vectorized core).

Figures (the issue's keys), each contender timed in alternating blocks so that this VM's speed
drifts hit all alike:

- ``batched_copy_steps_per_s_b1024`` / ``_b4096``: the batched vector env without calibrations;
  ``vmas_simple_spread_copy_steps_per_s_b4096`` (CPU, one torch thread) and their ratio
  ``batched_over_vmas_b4096``;
- ``batched_fixed10_over_nocal_b1024``: with a calibration every 10 steps per copy;
- ``single_fixed10_over_mpe``: one scheduler env with ``fixed:10`` vs PettingZoo MPE
  ``simple_spread`` (mpe2), steps/s;
- ``reset_s_b4096``: the first reset of 4096 copies in the process (it also loads the compiled
  kernels from numba's cache); ``reset_s_b4096_warm``: the median of the next three (what every
  later episode pays);
- ``sb3_ppo_steps_per_s_default`` (PPO on ``uwb-env train``'s default path: the batched copies,
  with that path's hyperparameters) and ``sb3_ppo_over_dummy8`` (over DummyVecEnv(8) of the
  Gymnasium scheduler env with its hyperparameters, the previous default);
- ``--before REV [REV ...]``: the batched figure at B = 1024 and the single env's ``fixed:10``
  rate of other revisions beside this tree's, in subprocesses on temporary worktrees interleaved
  with one of this tree (rev, current, rev, current, ...) -> ``batched_b1024_over_before`` (the
  first revision) and ``batched_b1024_over_<rev>`` / ``single_fixed10_over_<rev>`` for each;
- ``--fixed10-before REV``: the ``fixed:10`` / no-calibration ratio of another revision, the same
  way -> ``batched_fixed10_over_nocal_b1024_before``.

    python benchmarks/bench_vec.py [--quick] [--before 80cfb30 25a3f64] [--fixed10-before e8d8761]

Writes benchmarks/results/bench_vec.json (``_quick`` with --quick). Needs the ``bench`` extra
(vmas, mpe2) and ``train`` (SB3) for every figure; a missing one is reported as missing.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import print_table, write_results  # noqa: E402


def batched_stepper(b: int, fixed: int | None = None):
    from uwb_env.env.vector_env import CalibrationSchedulingVectorEnv

    env = CalibrationSchedulingVectorEnv(num_envs=b)
    env.reset(seed=0)
    t = [0]

    def step():
        t[0] += 1
        if fixed is None:
            env.step(np.zeros(b, dtype=np.int64))
        else:
            env.step(((np.arange(b) + t[0]) % fixed == 0).astype(np.int64))

    return step


def vmas_stepper(b: int):
    try:
        import torch
        import vmas
    except ImportError:
        return None
    torch.set_num_threads(1)
    env = vmas.make_env("simple_spread", num_envs=b, device="cpu", continuous_actions=True, seed=0)
    env.reset()
    actions = [torch.zeros(b, 2) for _ in env.agents]
    return lambda: env.step(actions)


def single_fixed10_stepper():
    from uwb_env.env.scheduler_env import CalibrationSchedulingEnv

    env = CalibrationSchedulingEnv(max_cycles=10**9)
    env.reset(seed=0)
    t = [0]

    def step():
        t[0] += 1
        env.step(int(t[0] % 10 == 0))

    return step


def mpe_stepper():
    try:
        from mpe2 import simple_spread_v3
    except ImportError:
        return None
    env = simple_spread_v3.parallel_env(max_cycles=10**9)
    env.reset(seed=0)
    actions = {a: 0 for a in env.agents}
    return lambda: env.step(actions)


def alternating(steppers: dict, per_call: dict, seconds: float, rounds: int) -> dict:
    """Best rate (copies x calls per second) of each stepper over alternating timed blocks."""
    best = {k: 0.0 for k in steppers}
    for _ in range(rounds):
        for name, fn in steppers.items():
            calls, t0 = 0, time.perf_counter()
            while time.perf_counter() - t0 < seconds / rounds:
                fn()
                calls += 1
            best[name] = max(best[name], per_call[name] * calls / (time.perf_counter() - t0))
    return best


def ppo_rate(env: str, vec_env: str, steps: int) -> float | None:
    """PPO env steps/s (rollouts and updates) on a training path with its own hyperparameters."""
    try:
        from stable_baselines3 import PPO
    except ImportError:
        return None
    import torch
    from uwb_env.training.train import Args, load_hyperparams, make_vec_env, resolve_env

    from uwb_env.config import EnvConfig

    torch.set_num_threads(1)
    config = EnvConfig().to_dict()
    args = Args(env=env, vec_env=vec_env)
    args = Args(env=resolve_env(args, config), vec_env=vec_env)
    hp = load_hyperparams(args)
    n_envs = int(hp.pop("n_envs", 1))
    for key in ("normalize", "norm_reward"):
        hp.pop(key, None)
    venv = make_vec_env(args.env, n_envs, config, seed=0, vec_env="dummy")
    model = PPO(hp.pop("policy", "MlpPolicy"), venv, seed=0, verbose=0, device="cpu", **hp)
    t0 = time.perf_counter()
    model.learn(total_timesteps=steps)
    return model.num_timesteps / (time.perf_counter() - t0)


def _tree_rates(tree: Path, seconds: float, fixed10: bool) -> dict:
    """Rates of the code in ``tree`` in a subprocess (this file's steppers on that tree's package):
    batched B = 1024 without calibrations, single env with ``fixed:10``, and with ``fixed10``
    the batched ``fixed:10`` copies."""
    steppers = "{'nocal': b.batched_stepper(1024), 'single': b.single_fixed10_stepper()"
    steppers += ", 'fixed10': b.batched_stepper(1024, 10)}" if fixed10 else "}"
    code = (f"import sys, json; sys.path.insert(0, {str(Path(__file__).parent)!r}); import bench_vec as b; "
            f"print(json.dumps(b.alternating({steppers}, {{'nocal': 1024, 'fixed10': 1024, 'single': 1}}, "
            f"{seconds}, 3)))")
    out = subprocess.run([sys.executable, "-c", code], env=dict(os.environ, PYTHONPATH=str(tree)), check=True,
                         capture_output=True, text=True, cwd=tree)
    return json.loads(out.stdout.strip().splitlines()[-1])


def before(revs: list[str], seconds: float, fixed10: bool = False, blocks: int = 2) -> dict:
    """Rates of other revisions beside this tree's, each in a subprocess on a temporary worktree,
    the subprocesses interleaved (rev 1, this tree, rev 2, this tree, ...) ``blocks`` times so that
    the VM's drift hits all alike; the best block of each. Returns {rev or "current": rates}."""
    root = Path(__file__).resolve().parents[1]
    best: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        trees = {}
        try:
            for rev in revs:
                trees[rev] = Path(tmp) / rev
                subprocess.run(["git", "-C", str(root), "worktree", "add", "--detach", str(trees[rev]), rev],
                               check=True, capture_output=True)
            for _ in range(blocks):
                for rev in revs:
                    for name, tree in ((rev, trees[rev]), ("current", root)):
                        rates = _tree_rates(tree, seconds, fixed10)
                        best[name] = {k: max(v, best.get(name, {}).get(k, 0.0)) for k, v in rates.items()}
        finally:
            for tree in trees.values():
                subprocess.run(["git", "-C", str(root), "worktree", "remove", "--force", str(tree)],
                               capture_output=True)
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--before", nargs="+", default=None,
                        help="git revisions whose batched B=1024 and single fixed:10 rates are set beside this "
                             "tree's (interleaved subprocesses); the first gives batched_b1024_over_before")
    parser.add_argument("--fixed10-before", default=None,
                        help="a git revision whose batched fixed:10 / no-calibration ratio at B=1024 is set beside")
    args = parser.parse_args()
    seconds = 3.0 if args.quick else 12.0
    fig: dict = {}

    from uwb_env.env.vector_env import CalibrationSchedulingVectorEnv

    env = CalibrationSchedulingVectorEnv(num_envs=4096)
    t0 = time.perf_counter()
    env.reset(seed=0)
    fig["reset_s_b4096"] = time.perf_counter() - t0
    warm = []
    for seed in (1, 2, 3):  # the per-episode cost: the compiled kernels are loaded by now
        t0 = time.perf_counter()
        env.reset(seed=seed)
        warm.append(time.perf_counter() - t0)
    fig["reset_s_b4096_warm"] = float(np.median(warm))
    del env

    steppers = {"batched_b1024": batched_stepper(1024), "batched_b1024_fixed10": batched_stepper(1024, 10),
                "batched_b4096": batched_stepper(4096)}
    per_call = {"batched_b1024": 1024, "batched_b1024_fixed10": 1024, "batched_b4096": 4096}
    vm = vmas_stepper(4096)
    if vm is not None:
        steppers["vmas_b4096"], per_call["vmas_b4096"] = vm, 4096
    rates = alternating(steppers, per_call, seconds, 3)
    single = {"single_fixed10": single_fixed10_stepper()}
    mpe = mpe_stepper()
    if mpe is not None:
        single["mpe"] = mpe
    rates.update(alternating(single, {k: 1 for k in single}, seconds / 2, 3))

    fig["batched_copy_steps_per_s_b1024"] = rates["batched_b1024"]
    fig["batched_copy_steps_per_s_b4096"] = rates["batched_b4096"]
    fig["batched_fixed10_copy_steps_per_s_b1024"] = rates["batched_b1024_fixed10"]
    fig["batched_fixed10_over_nocal_b1024"] = rates["batched_b1024_fixed10"] / rates["batched_b1024"]
    fig["single_fixed10_steps_per_s"] = rates["single_fixed10"]
    if vm is not None:
        fig["vmas_simple_spread_copy_steps_per_s_b4096"] = rates["vmas_b4096"]
        fig["batched_over_vmas_b4096"] = rates["batched_b4096"] / rates["vmas_b4096"]
    if mpe is not None:
        fig["mpe_simple_spread_steps_per_s"] = rates["mpe"]
        fig["single_fixed10_over_mpe"] = rates["single_fixed10"] / rates["mpe"]
    steps = 8192 if args.quick else 32768
    default, dummy = ppo_rate("scheduler", "auto", steps), ppo_rate("scheduler", "dummy", steps)
    if default is not None:
        fig["sb3_ppo_steps_per_s_default"] = default  # `uwb-env train`'s default path: batched copies
        fig["sb3_ppo_steps_per_s_dummy8"] = dummy
        fig["sb3_ppo_over_dummy8"] = default / dummy
    if args.before:
        # the first revision gives the keys; every revision its own, all measured in one
        # interleaved series beside this tree (rates of the same run, not of the blocks above)
        cmp = before(args.before, seconds)
        first = args.before[0]
        fig["before_revision"] = first
        fig["batched_copy_steps_per_s_b1024_before"] = cmp[first]["nocal"]
        fig["batched_b1024_over_before"] = cmp["current"]["nocal"] / cmp[first]["nocal"]
        for rev in args.before:
            fig[f"batched_b1024_over_{rev}"] = cmp["current"]["nocal"] / cmp[rev]["nocal"]
            fig[f"single_fixed10_over_{rev}"] = cmp["current"]["single"] / cmp[rev]["single"]

    if args.fixed10_before:
        rates_before = before([args.fixed10_before], seconds, fixed10=True, blocks=1)[args.fixed10_before]
        fig["fixed10_before_revision"] = args.fixed10_before
        fig["batched_fixed10_over_nocal_b1024_before"] = rates_before["fixed10"] / rates_before["nocal"]

    rows = [[k, v] for k, v in fig.items() if isinstance(v, float)]
    print_table("Batched mode throughput (copy-steps/s; ratios side by side in one run)", ["figure", "value"], rows)
    write_results("bench_vec_quick" if args.quick else "bench_vec", fig, args.quick)
    print(json.dumps({k: fig[k] for k in ("batched_over_vmas_b4096", "batched_fixed10_over_nocal_b1024")
                      if k in fig}))


if __name__ == "__main__":
    main()
