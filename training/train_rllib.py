"""Multi-agent PPO on the ParallelEnv with Ray RLlib (new API stack), locally or on a cluster.

Usage (also ``uwb-env train --backend rllib``)::

    python -m uwb_env.training.train_rllib --iterations 50 --out runs/rllib                # local Ray instance
    python -m uwb_env.training.train_rllib --address auto --num-env-runners 8 ...          # an existing cluster

The env goes through RLlib's ``ParallelPettingZooEnv``; by default one RLModule ``shared`` is
used by every anchor (``--policy per_anchor``: one module per anchor). Hyperparameters come
from ``training/hyperparams/rllib_ppo.yml`` (same style as the SB3 files), overridable with
``--hp key=value``. The output folder holds ``checkpoint/`` (the Algorithm checkpoint; running
the same command again resumes from it) and ``run.json`` with the same keys as the SB3 runs.
``agents/learned_rllib.py`` loads the checkpoint behind the policy hook
(``rllib:runs/rllib/checkpoint`` in ``uwb-env evaluate``).
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from uwb_env.training.hyperparams_io import load_block

HYPERPARAMS = Path(__file__).with_name("hyperparams") / "rllib_ppo.yml"
ENV_ID = "uwb_env/Parallel-v0"
ENV_NAME = "uwb_env_parallel"


@dataclass
class Args:
    iterations: int = 20
    out: str = "runs/rllib"
    seed: int = 0
    address: str | None = None
    """Ray cluster address (``auto`` or ``HOST:PORT``); None starts a local instance"""
    num_env_runners: int = 1
    num_envs_per_env_runner: int = 1
    policy: str = "shared"
    """``shared`` (one module for all anchors) or ``per_anchor``"""
    hyperparams: str | None = None
    hp: list[str] = field(default_factory=list)
    env_config: str | None = None
    resume: bool = True
    checkpoint_every: int = 5


def load_hyperparams(args: Args) -> dict:
    return load_block(Path(args.hyperparams) if args.hyperparams else HYPERPARAMS, ENV_ID, args.hp)


def _make_env(cfg: dict):
    from ray.rllib.env.wrappers.pettingzoo_env import ParallelPettingZooEnv

    import uwb_env

    return ParallelPettingZooEnv(uwb_env.parallel_env(config=cfg["config"]))


def build_config(args: Args, env_config: dict, hp: dict):
    from ray.rllib.algorithms.ppo import PPOConfig
    from ray.rllib.core.rl_module.default_model_config import DefaultModelConfig
    from ray.rllib.core.rl_module.multi_rl_module import MultiRLModuleSpec
    from ray.rllib.core.rl_module.rl_module import RLModuleSpec
    from ray.tune.registry import register_env

    from uwb_env.config import EnvConfig

    if args.policy not in ("shared", "per_anchor"):
        raise ValueError(f"policy={args.policy!r}: must be 'shared' or 'per_anchor'")
    register_env(ENV_NAME, _make_env)
    n = EnvConfig.from_dict(env_config).sim.n_anchors
    policies = {"shared"} if args.policy == "shared" else {f"anchor_{i}" for i in range(n)}
    hp = dict(hp)
    hidden = hp.pop("fcnet_hiddens", [64, 64])
    mapping = (lambda agent_id, episode, **kw: "shared") if args.policy == "shared" else (
        lambda agent_id, episode, **kw: agent_id)
    return (
        PPOConfig()
        .environment(ENV_NAME, env_config={"config": env_config})
        .env_runners(num_env_runners=args.num_env_runners, num_envs_per_env_runner=args.num_envs_per_env_runner)
        .multi_agent(policies=policies, policy_mapping_fn=mapping)
        .rl_module(rl_module_spec=MultiRLModuleSpec(rl_module_specs={p: RLModuleSpec() for p in policies}),
                   model_config=DefaultModelConfig(fcnet_hiddens=hidden))
        .training(**hp)
        .debugging(seed=args.seed)
    )


def main(args: Args) -> dict:
    import ray

    from uwb_env.cli import load_overrides
    from uwb_env.config import EnvConfig

    hp = load_hyperparams(args)
    env_config = EnvConfig.from_dict(load_overrides(args.env_config)).to_dict()
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    checkpoint = out / "checkpoint"
    if not ray.is_initialized():
        ray.init(address=args.address, include_dashboard=False, log_to_driver=False,
                 **({} if args.address else {"num_cpus": max(2, args.num_env_runners + 1)}))
    algo = build_config(args, env_config, hp).build_algo()
    resumed = 0
    if args.resume and (checkpoint / "rllib_checkpoint.json").exists():
        algo.restore_from_path(str(checkpoint))
        resumed = int(json.loads((out / "run.json").read_text()).get("iterations_done", 0))
    start, history = time.perf_counter(), []
    steps_before = steps = int(json.loads((out / "run.json").read_text()).get("num_timesteps", 0)) if resumed else 0
    iterations_done = resumed
    for _ in range(max(args.iterations - resumed, 0)):
        result = algo.train()
        iterations_done += 1
        history.append(_metrics(result))
        steps = _env_steps(result, steps)
        if iterations_done % args.checkpoint_every == 0 or iterations_done == args.iterations:
            algo.save_to_path(str(checkpoint))
    wall = time.perf_counter() - start
    if not (checkpoint / "rllib_checkpoint.json").exists():
        algo.save_to_path(str(checkpoint))
    record = {
        "algo": "rllib_ppo", "env": "parallel", "env_id": ENV_ID, "args": asdict(args), "hyperparams": hp,
        "env_config": env_config, "policy": args.policy, "iterations_done": iterations_done,
        "num_timesteps": steps, "resumed_from_iterations": resumed, "training_wall_s": wall,
        "env_steps_per_s": (steps - steps_before) / max(wall, 1e-9), "history": history,
        "checkpoint": str(checkpoint),
    }
    (out / "run.json").write_text(json.dumps(record, indent=1, default=str))
    algo.stop()
    return record


def _env_steps(result: dict, previous: int) -> int:
    for source in (result, result.get("env_runners", {})):
        value = source.get("num_env_steps_sampled_lifetime")
        if value:
            return int(value)
    return previous


def _metrics(result: dict) -> dict:
    runners = result.get("env_runners", {})
    return {"episode_return_mean": runners.get("episode_return_mean"),
            "env_steps_sampled": runners.get("num_env_steps_sampled_lifetime")}


def add_arguments(p: argparse.ArgumentParser) -> None:
    d = Args()
    p.add_argument("--iterations", type=int, default=d.iterations)
    p.add_argument("--out", default=d.out)
    p.add_argument("--seed", type=int, default=d.seed)
    p.add_argument("--address", default=None, help="Ray cluster address (auto or HOST:PORT); default: local")
    p.add_argument("--num-env-runners", type=int, default=d.num_env_runners)
    p.add_argument("--num-envs-per-env-runner", type=int, default=d.num_envs_per_env_runner)
    p.add_argument("--policy", choices=("shared", "per_anchor"), default=d.policy)
    p.add_argument("--hyperparams", default=None)
    p.add_argument("--hp", nargs="*", default=[])
    p.add_argument("--env-config", default=None)
    p.add_argument("--no-resume", dest="resume", action="store_false")
    p.add_argument("--checkpoint-every", type=int, default=d.checkpoint_every)


def args_from_namespace(ns: argparse.Namespace) -> Args:
    return Args(**{k: getattr(ns, k) for k in asdict(Args()) if hasattr(ns, k)})


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_arguments(parser)
    rec = main(args_from_namespace(parser.parse_args()))
    print(json.dumps({k: rec[k] for k in ("iterations_done", "num_timesteps", "training_wall_s")}, indent=1))
