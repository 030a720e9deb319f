"""Train a calibration scheduler with stable-baselines3 (PPO by default; DQN, A2C).

Usage (also ``uwb-env train``)::

    python -m uwb_env.training.train --algo ppo --env scheduler --total-timesteps 200000 --out runs/ppo

``--env scheduler``: the centralized Gymnasium env (one decision for the team).
``--env parallel``: decentralized anchors over the PettingZoo env, one policy shared by all
anchors through :class:`training.vec_env.ParallelEnvVecEnv`.

Hyperparameters come from ``training/hyperparams/<algo>.yml`` (rl-zoo style, one block per
env id), overridden by ``--hp key=value``. The output folder holds ``model.zip``,
``vecnormalize.pkl`` (observation statistics), ``run.json`` (arguments, hyperparameters, env
config, metrics), ``checkpoints/`` and TensorBoard logs in ``tb/``. Running the same command
again after a kill resumes from the newest checkpoint. Training seeds are ``seed + i``; the
``EvalCallback`` uses validation seeds from ``VALIDATION_SEED_BASE``; the evaluation harness
uses its own held-out seeds (``training.evaluate.EVAL_SEED_BASE``).
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import re
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from uwb_env.training.hyperparams_io import load_block

ALGOS = ("ppo", "a2c", "dqn")
# "batched": the scheduler task, with all training copies stepped together in numpy
ENV_IDS = {"scheduler": "uwb_env/CalibrationScheduling-v0", "parallel": "uwb_env/Parallel-v0",
           "batched": "uwb_env/CalibrationScheduling-batched"}
VALIDATION_SEED_BASE = 500_000
HYPERPARAMS_DIR = Path(__file__).with_name("hyperparams")


@dataclass
class Args:
    algo: str = "ppo"
    env: str = "scheduler"
    """``scheduler`` (centralized) or ``parallel`` (shared policy over the anchors)"""
    total_timesteps: int = 200_000
    seed: int = 0
    out: str = "runs/train"
    hyperparams: str | None = None
    """YAML file (default: training/hyperparams/<algo>.yml)"""
    hp: list[str] = field(default_factory=list)
    """hyperparameter overrides, ``key=value`` (value parsed as YAML)"""
    env_config: str | None = None
    """YAML/JSON file with EnvConfig overrides (the scenario)"""
    vec_env: str = "auto"
    """``auto`` (scheduler env: the batched copies where the env config allows it, 2D with the
    ``calibrate`` action mode, else ``dummy``), ``dummy`` or ``subproc``"""
    checkpoint_freq: int = 20_000
    """env steps between checkpoints"""
    eval_freq: int = 20_000
    """env steps between EvalCallback evaluations (0: none)"""
    eval_episodes: int = 4
    progress_bar: bool = True
    tensorboard: bool = True
    resume: bool = True
    """continue from the newest checkpoint in ``out/checkpoints`` if there is one"""
    torch_threads: int = 1
    max_wall_s: float | None = None
    """stop training after this many seconds (the model is saved as usual)"""
    verbose: int = 0


def load_hyperparams(args: Args) -> dict:
    path = Path(args.hyperparams) if args.hyperparams else HYPERPARAMS_DIR / f"{args.algo}.yml"
    return load_block(path, ENV_IDS[args.env], args.hp)


def _check(args: Args) -> None:
    if args.algo not in ALGOS:
        raise ValueError(f"algo={args.algo!r}: must be one of {ALGOS}")
    if args.env not in ENV_IDS:
        raise ValueError(f"env={args.env!r}: must be one of {tuple(ENV_IDS)}")
    if args.vec_env not in ("auto", "dummy", "subproc"):
        raise ValueError(f"vec_env={args.vec_env!r}: must be 'auto', 'dummy' or 'subproc'")
    if args.total_timesteps < 1:
        raise ValueError(f"total_timesteps={args.total_timesteps!r}: must be >= 1")


def resolve_env(args: Args, env_config: dict) -> str:
    """The env path ``main`` trains on: ``--env scheduler`` with ``--vec-env auto`` takes the
    batched copies (one numpy step for all of them; same observations, reward and dynamics,
    tested) when the config allows it: 2D and the ``calibrate`` action mode."""
    if args.env != "scheduler" or args.vec_env != "auto":
        return args.env
    sim = env_config.get("sim", {})
    batchable = sim.get("dim", 2) == 2 and env_config.get("action_mode", "calibrate") == "calibrate"
    return "batched" if batchable else "scheduler"


def make_vec_env(kind: str, n_envs: int, env_config: dict, seed: int, vec_env: str = "dummy"):
    """The training (or evaluation) VecEnv, seeded so that copy i resets with ``seed + i``."""
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecMonitor

    import uwb_env  # noqa: F401  (registers the Gymnasium id)

    if kind == "batched":
        from uwb_env.training.vec_env import BatchedSchedulerVecEnv

        venv = BatchedSchedulerVecEnv(n_envs, env_config)
        venv.seed(seed)
        return VecMonitor(venv)
    if kind == "scheduler":
        fns = [functools.partial(_make_scheduler_env, env_config) for _ in range(n_envs)]
        venv = SubprocVecEnv(fns) if vec_env == "subproc" and n_envs > 1 else DummyVecEnv(fns)
    else:
        from uwb_env.training.vec_env import ParallelEnvVecEnv

        venv = ParallelEnvVecEnv([lambda: uwb_env.parallel_env(config=env_config) for _ in range(n_envs)])
    venv.seed(seed)
    return VecMonitor(venv)


def _make_scheduler_env(env_config: dict):
    # Module-level (picklable) and importing uwb_env itself, so SubprocVecEnv workers can use it.
    import gymnasium as gym

    import uwb_env  # noqa: F401  (registers the id)

    return gym.make(ENV_IDS["scheduler"], config=env_config)


def _check_hyperparams(algo_cls, hp: dict) -> None:
    import difflib
    import inspect

    accepted = set(inspect.signature(algo_cls.__init__).parameters) - {"self", "policy", "env", "_init_setup_model"}
    for key in sorted(set(hp) - accepted):
        close = difflib.get_close_matches(key, sorted(accepted), n=1)
        hint = f"; did you mean {close[0]}?" if close else f"; known: {', '.join(sorted(accepted))}"
        raise ValueError(f"--hp {key}={hp[key]} (or the hyperparameters YAML): not a {algo_cls.__name__} "
                         f"hyperparameter{hint}")


def latest_checkpoint(folder: Path) -> tuple[Path, int] | None:
    best = None
    for path in folder.glob("model_*_steps.zip"):
        m = re.fullmatch(r"model_(\d+)_steps\.zip", path.name)
        if m and (best is None or int(m.group(1)) > best[1]):
            best = (path, int(m.group(1)))
    return best


def main(args: Args) -> dict:
    """Train (or resume); returns the run record also written to ``out/run.json``."""
    import stable_baselines3 as sb3
    from stable_baselines3.common.callbacks import CallbackList, CheckpointCallback
    from stable_baselines3.common.vec_env import VecNormalize

    from uwb_env.cli import load_overrides
    from uwb_env.config import EnvConfig

    _check(args)
    import torch

    torch.set_num_threads(args.torch_threads)  # small MLPs: threads cost more than they give
    env_config = EnvConfig.from_dict(load_overrides(args.env_config, "--env-config")).to_dict()
    requested = args.env
    args = dataclasses.replace(args, env=resolve_env(args, env_config))
    if args.env != requested:
        print(f"train: --env {requested} on the batched copies (--vec-env dummy for one Gymnasium env per copy)",
              flush=True)
    hp = load_hyperparams(args)
    n_envs = int(hp.pop("n_envs", 1))
    normalize = bool(hp.pop("normalize", False))
    norm_reward = bool(hp.pop("norm_reward", False))
    policy = hp.pop("policy", "MlpPolicy")
    algo_cls = {"ppo": sb3.PPO, "a2c": sb3.A2C, "dqn": sb3.DQN}[args.algo]
    _check_hyperparams(algo_cls, hp)  # before any folder exists: a typo leaves nothing behind
    out = Path(args.out)
    ckpt_dir = out / "checkpoints"
    ckpt_dir.mkdir(parents=True, exist_ok=True)

    venv = make_vec_env(args.env, n_envs, env_config, args.seed, args.vec_env)
    # validation on the single env (the batched mode has the same observations and reward)
    eval_env = make_vec_env("scheduler" if args.env == "batched" else args.env, 1, env_config, VALIDATION_SEED_BASE)
    resume = latest_checkpoint(ckpt_dir) if args.resume else None
    if normalize:
        stats = ckpt_dir / f"model_vecnormalize_{resume[1]}_steps.pkl" if resume else None
        if stats is not None and stats.exists():
            venv = VecNormalize.load(str(stats), venv)
        else:
            venv = VecNormalize(venv, norm_obs=True, norm_reward=norm_reward)
        eval_env = VecNormalize(eval_env, norm_obs=True, norm_reward=False, training=False)
    tb = str(out / "tb") if args.tensorboard and _has_tensorboard() else None
    if resume:
        model = algo_cls.load(str(resume[0]), env=venv, device="cpu", tensorboard_log=tb)
        buffer = ckpt_dir / f"model_replay_buffer_{resume[1]}_steps.pkl"
        if args.algo == "dqn" and buffer.exists():
            model.load_replay_buffer(str(buffer))
    else:
        model = algo_cls(policy, venv, seed=args.seed, device="cpu", tensorboard_log=tb, verbose=args.verbose, **hp)
    per_call = venv.num_envs
    callbacks = [CheckpointCallback(save_freq=max(args.checkpoint_freq // per_call, 1), save_path=str(ckpt_dir),
                                    name_prefix="model", save_replay_buffer=args.algo == "dqn",
                                    save_vecnormalize=normalize)]
    if args.eval_freq > 0:
        callbacks.append(_synced_eval(eval_env, n_eval_episodes=args.eval_episodes,
                                     eval_freq=max(args.eval_freq // per_call, 1), log_path=str(out / "eval"),
                                     best_model_save_path=str(out / "best"), deterministic=True, verbose=0))
    if args.max_wall_s is not None:
        callbacks.append(_wall_clock_limit(args.max_wall_s))
    remaining = args.total_timesteps - model.num_timesteps
    rollout = getattr(model, "n_steps", 0) * venv.num_envs  # PPO/A2C learn in whole rollouts
    if rollout and remaining > 0 and remaining % rollout:
        remaining = -(-remaining // rollout) * rollout  # what SB3 runs anyway; the progress bar's total says so
        print(f"{args.algo}: whole rollouts of {rollout} steps: training to {model.num_timesteps + remaining:,} "
              f"steps (asked {args.total_timesteps:,})", flush=True)
    start = time.perf_counter()
    if remaining > 0:
        model.learn(remaining, callback=CallbackList(callbacks), reset_num_timesteps=resume is None,
                    progress_bar=args.progress_bar and _has_progress_bar(), tb_log_name=args.algo)
    wall = time.perf_counter() - start
    model.save(str(out / "model.zip"))
    if normalize:
        venv.save(str(out / "vecnormalize.pkl"))
    record = {
        "algo": args.algo, "env": args.env, "env_id": ENV_IDS[args.env], "args": asdict(args),
        "hyperparams": {**hp, "n_envs": n_envs, "normalize": normalize, "norm_reward": norm_reward, "policy": policy},
        "env_config": env_config, "num_timesteps": int(model.num_timesteps),
        "resumed_from_steps": resume[1] if resume else 0, "training_wall_s": wall,
        "env_steps_per_s": (model.num_timesteps - (resume[1] if resume else 0)) / max(wall, 1e-9),
    }
    evals = [c for c in callbacks if hasattr(c, "evaluations_results")]
    if evals and evals[0].evaluations_results:
        record["last_eval_mean_reward"] = float(evals[0].last_mean_reward)
        record["best_eval_mean_reward"] = float(evals[0].best_mean_reward)
        means = [float(sum(r) / len(r)) for r in evals[0].evaluations_results]
        record["best_eval_timesteps"] = int(evals[0].evaluations_timesteps[means.index(max(means))])
    if args.eval_freq > 0 and not (evals and evals[0].evaluations_results):
        print(f"note: no validation ran (--eval-freq {args.eval_freq:,} > {model.num_timesteps:,} steps trained): "
              f"{out / 'best'} and {out / 'eval'} are empty", flush=True)
    (out / "run.json").write_text(json.dumps(record, indent=1, default=str))
    _complete_best_model(out, ckpt_dir, record, normalize)
    venv.close()
    eval_env.close()
    return record


def _complete_best_model(out: Path, ckpt_dir: Path, record: dict, normalize: bool) -> None:
    """Make ``best/`` loadable like the final model: the run record, and the observation
    statistics the EvalCallback used (the checkpoint's at or before the best evaluation)."""
    best = out / "best" / "best_model.zip"
    if not best.exists() or "best_eval_timesteps" not in record:
        return
    (out / "best" / "run.json").write_text(json.dumps(record, indent=1, default=str))
    if normalize:
        stats = sorted((int(m.group(1)), p) for p in ckpt_dir.glob("model_vecnormalize_*_steps.pkl")
                       if (m := re.fullmatch(r"model_vecnormalize_(\d+)_steps\.pkl", p.name))
                       and int(m.group(1)) <= record["best_eval_timesteps"])
        if stats:
            shutil.copy(stats[-1][1], out / "best" / "vecnormalize.pkl")


def _synced_eval(eval_env, **kwargs):
    """An EvalCallback whose evaluation env uses the training env's current normalization
    (defined here so that importing this module does not need SB3)."""
    from stable_baselines3.common.callbacks import EvalCallback
    from stable_baselines3.common.vec_env import VecNormalize

    class SyncedEval(EvalCallback):
        def _on_step(self) -> bool:
            train_env = self.model.get_env()
            if isinstance(train_env, VecNormalize) and isinstance(self.eval_env, VecNormalize):
                self.eval_env.obs_rms = train_env.obs_rms.copy()
            return super()._on_step()

    return SyncedEval(eval_env, **kwargs)


def _wall_clock_limit(seconds: float):
    from stable_baselines3.common.callbacks import BaseCallback

    class WallClockLimit(BaseCallback):
        def _on_training_start(self) -> None:
            self.deadline = time.perf_counter() + seconds

        def _on_step(self) -> bool:
            return time.perf_counter() < self.deadline

    return WallClockLimit()


def _has_tensorboard() -> bool:
    try:
        import tensorboard  # noqa: F401
    except ImportError:
        return False
    return True


def _has_progress_bar() -> bool:
    try:
        import rich  # noqa: F401
        import tqdm  # noqa: F401
    except ImportError:
        return False
    return True


def add_arguments(p: argparse.ArgumentParser) -> None:
    d = Args()
    p.add_argument("--algo", choices=ALGOS, default=d.algo, help="sb3 algorithm")
    p.add_argument("--env", choices=tuple(ENV_IDS), default=d.env,
                   help="scheduler: one central decision; parallel: per-anchor agents sharing a policy; batched: many "
                        "scheduler copies in numpy")
    p.add_argument("--total-timesteps", type=int, default=d.total_timesteps,
                   help="env steps (on-policy algorithms round up to whole rollouts)")
    p.add_argument("--seed", type=int, default=d.seed, help="training seed")
    p.add_argument("--out", default=d.out, help="output folder (model.zip, run.json, checkpoints/, best/, eval/; "
                   "rllib: runs/rllib)")
    p.add_argument("--hyperparams", default=None, help="YAML file (default: training/hyperparams/<algo>.yml)")
    p.add_argument("--hp", nargs="*", default=[], help="overrides key=value, e.g. learning_rate=1e-4")
    p.add_argument("--env-config", default=None, help="YAML/JSON file with EnvConfig overrides")
    p.add_argument("--vec-env", choices=("auto", "dummy", "subproc"), default=d.vec_env,
                   help="auto: the batched copies where the env config allows (2D, calibrate action mode); "
                   "dummy/subproc: SB3 vector env classes over Gymnasium envs")
    p.add_argument("--checkpoint-freq", type=int, default=d.checkpoint_freq, help="env steps between checkpoints")
    p.add_argument("--eval-freq", type=int, default=d.eval_freq,
                   help="env steps between validation runs (best/ and eval/); 0 = none")
    p.add_argument("--eval-episodes", type=int, default=d.eval_episodes, help="episodes per validation run")
    p.add_argument("--no-progress-bar", dest="progress_bar", action="store_false")
    p.add_argument("--no-tensorboard", dest="tensorboard", action="store_false")
    p.add_argument("--no-resume", dest="resume", action="store_false", help="start fresh even if checkpoints exist")
    p.add_argument("--max-wall-s", type=float, default=None, help="stop after this many seconds")
    p.add_argument("--verbose", type=int, default=d.verbose, help="SB3 verbosity")


def args_from_namespace(ns: argparse.Namespace) -> Args:
    return Args(**{k: getattr(ns, k) for k in asdict(Args()) if hasattr(ns, k)})


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_arguments(parser)
    record = main(args_from_namespace(parser.parse_args()))
    print(json.dumps({k: record[k] for k in ("num_timesteps", "training_wall_s", "env_steps_per_s")}, indent=1))
