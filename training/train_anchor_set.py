"""Train the team-size-invariant per-anchor scheduler (PPO, one policy shared by all anchors).

Usage::

    python -m uwb_env.training.train_anchor_set --seed 0 --out runs/anchor_set/seed0 --max-wall-s 1500

Every anchor of every training copy is one PPO slot (parameter sharing); it sees
:func:`uwb_env.agents.anchor_set.anchor_set_features` (its own features and the mean / max of
the others', team size, step length) and picks a ``per_anchor`` action: nothing, re-locate me,
request a team round. The team reward is every anchor's reward. The copies have the team sizes
of ``training/distributions/anchor_set.yml`` and draw a new scenario (motion speed, drift,
radio, area, tags, step length) every episode, from training seeds only.

Every ``eval_every_steps`` the policy is scored on validation seeds (mean env return over the
suite's training-side scenarios: default, harsh radio, fast robots, low drift, five and eight
anchors); the best scoring one is saved in ``out/best/`` (model.zip, vecnormalize.pkl,
run.json): the checkpoint is chosen on validation seeds, never on test seeds. ``out/checkpoints``
holds the latest state; running the same command again after a kill resumes from it.

The batched env (uwb_env.batch) does not have the per_anchor actions; these copies run as
PettingZoo ParallelEnvs (``training.vec_env.AnchorSetVecEnv``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import yaml
from uwb_env.training.hyperparams_io import load_block

HERE = Path(__file__).resolve().parent
ENV_ID = "uwb_env/AnchorSet"
DEFAULT_DISTRIBUTION = HERE / "distributions" / "anchor_set.yml"
DEFAULT_HYPERPARAMS = HERE / "hyperparams" / "ppo.yml"
TRAINING_SEED_SPAN = 500_000  # the suite's training range is [0, 499999]
VALIDATION_SEED_BASE = 500_000
VALIDATION_SCENARIOS = ("default", "harsh_radio", "fast_robots", "low_drift", "five_anchors", "eight_anchors")
# Each validation scenario runs the residual on its own tuned base threshold, as deployments
# (and the benchmark) do: validated on one threshold for all, a checkpoint is rewarded for
# repairing a mistuned base, which hurts on a tuned one.
VALIDATION_BASE_THRESHOLDS = HERE / "tuned" / "suite_per_anchor_threshold.json"


@dataclass
class Args:
    seed: int = 0
    out: str = "runs/anchor_set/seed0"
    total_timesteps: int = 5_000_000
    """anchor decisions (slots x steps)"""
    max_wall_s: float | None = 1500.0
    """stop training after this many seconds (the best and latest models are kept)"""
    distribution: str = str(DEFAULT_DISTRIBUTION)
    hyperparams: str = str(DEFAULT_HYPERPARAMS)
    hp: list[str] = dataclasses.field(default_factory=list)
    eval_every_steps: int = 250_000
    checkpoint_every_steps: int = 50_000
    """the latest state (model, statistics, scenario stream) for resuming after a kill"""
    val_episodes_per_scenario: int = 4
    val_max_cycles: int | None = None
    """shorter validation episodes (tests); None: the scenarios' own"""
    resume: bool = True
    torch_threads: int = 1
    verbose: int = 0


@dataclass(frozen=True)
class ScenarioDistribution:
    """training/distributions/anchor_set.yml; unknown keys are an error."""

    team_sizes: tuple[int, ...]
    episode_s: float
    dt_s: tuple[float, ...]
    n_tags: tuple[int, ...]
    area_size_m: tuple[float, float]
    speed_max_mps: tuple[float, float]
    odometry_scale: tuple[float, float]
    slip_rate_per_s: tuple[float, float]
    nlos_probability: tuple[float, float]
    dropout_probability: tuple[float, float]
    base_threshold_m: tuple[float, float]
    """the residual's base rule threshold, log-uniform (tuned per deployment, so trained on a range)"""

    @classmethod
    def load(cls, path: str | Path) -> ScenarioDistribution:
        with open(path) as f:
            raw = yaml.safe_load(f) or {}
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(raw) - names)
        if unknown:
            raise ValueError(f"distribution={str(path)!r}: unknown keys {unknown}; known: {sorted(names)}")
        missing = sorted(names - set(raw))
        if missing:
            raise ValueError(f"distribution={str(path)!r}: missing keys {missing}")
        out = cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in raw.items()})
        lo, hi = out.base_threshold_m
        if not 0 < lo <= hi:
            raise ValueError(f"base_threshold_m={list(out.base_threshold_m)!r}: needs 0 < low <= high")
        if any(int(n) < 3 for n in out.team_sizes):
            raise ValueError(f"team_sizes={list(out.team_sizes)!r}: every team needs at least 3 anchors")
        return out

    def sample_base_threshold(self, rng: np.random.Generator) -> float:
        lo, hi = self.base_threshold_m
        return float(np.exp(rng.uniform(np.log(lo), np.log(hi))))

    def sample(self, n_anchors: int, rng: np.random.Generator) -> dict:
        """EnvConfig overrides of one training episode (``per_anchor`` actions)."""
        from uwb_env.config import OdometryConfig

        def uniform(bounds):
            return float(rng.uniform(*bounds))

        dt = float(rng.choice(self.dt_s))
        speed = uniform(self.speed_max_mps)
        motion = {"speed_min_mps": 0.5 * speed, "speed_max_mps": speed}
        odo, scale = OdometryConfig(), uniform(self.odometry_scale)
        return {
            "action_mode": "per_anchor",
            "max_cycles": int(round(self.episode_s / dt)),
            "sim": {
                "n_anchors": int(n_anchors), "n_tags": int(rng.choice(self.n_tags)), "dt_s": dt,
                "area_size_m": uniform(self.area_size_m),
                "anchor_motion": motion, "tag_motion": dict(motion),
                "odometry": {"noise_std_m_per_sqrt_m": scale * odo.noise_std_m_per_sqrt_m,
                             "scale_error_std": scale * odo.scale_error_std,
                             "yaw_noise_std_rad_per_sqrt_m": scale * odo.yaw_noise_std_rad_per_sqrt_m,
                             "slip_rate_per_s": uniform(self.slip_rate_per_s)},
                "ranging": {"nlos_probability": uniform(self.nlos_probability),
                            "dropout_probability": uniform(self.dropout_probability)},
            },
        }


def validation_base_thresholds() -> dict[str, float]:
    """Scenario -> the per-anchor threshold tuned on its validation seeds (the residual's base)."""
    return {k: float(v) for k, v in json.loads(VALIDATION_BASE_THRESHOLDS.read_text())["base_threshold_m"].items()}


def validation_jobs(args: Args) -> list[tuple[str, int, dict]]:
    """(scenario, seed, env config overrides) of the checkpoint choice: validation seeds only."""
    from uwb_env.training.suite import load_suite

    suite = load_suite()
    jobs = []
    for name in VALIDATION_SCENARIOS:
        sc = suite[name]
        config = {**sc["config"], "max_cycles": args.val_max_cycles or sc["max_cycles"]}
        first = sc["seeds"]["validation"][0]
        jobs += [(name, first + i, config) for i in range(args.val_episodes_per_scenario)]
    return jobs


def validation_score(policy, jobs) -> float:
    """Mean env return of ``policy`` over the validation jobs (higher is better), each scenario
    on its tuned base threshold."""
    from uwb_env.agents.anchor_set import DEFAULT_BASE_THRESHOLD_M
    from uwb_env.training.evaluate import run_policy_episode

    bases = validation_base_thresholds()
    returns = []
    for name, seed, config in jobs:
        policy.base_threshold_m = bases.get(name, DEFAULT_BASE_THRESHOLD_M)
        returns.append(run_policy_episode(policy, seed, config)["return"])
    return float(np.mean(returns))


def _save(model, venv, out: Path, record: dict) -> None:
    out.mkdir(parents=True, exist_ok=True)
    model.save(out / "model.zip")
    venv.save(str(out / "vecnormalize.pkl"))
    (out / "run.json").write_text(json.dumps(record, indent=2, default=str))


def main(args: Args) -> dict:
    import torch
    from stable_baselines3 import PPO
    from stable_baselines3.common.callbacks import BaseCallback
    from uwb_env.agents.anchor_set import AnchorSetPolicy
    from uwb_env.agents.prior_policy import PartialVecNormalize, PriorLogitsPolicy
    from uwb_env.training.vec_env import AnchorSetVecEnv

    torch.set_num_threads(args.torch_threads)
    out = Path(args.out)
    dist = ScenarioDistribution.load(args.distribution)
    hp = load_block(args.hyperparams, ENV_ID, args.hp)
    normalize, norm_reward = hp.pop("normalize", True), hp.pop("norm_reward", True)
    policy_name = hp.pop("policy", "PriorLogitsPolicy")
    policy_class = {"PriorLogitsPolicy": PriorLogitsPolicy}.get(policy_name, policy_name)
    rng = np.random.default_rng([args.seed, 7])  # the scenario draws of this training seed
    seed_base = (args.seed * 100_003) % TRAINING_SEED_SPAN
    venv = base = AnchorSetVecEnv(dist, rng, seed_base, TRAINING_SEED_SPAN)
    ckpt = out / "checkpoints"
    state_path = ckpt / "state.json"
    resumed = args.resume and state_path.exists()
    if resumed:
        state = json.loads(state_path.read_text())
        # continue the scenario stream where it stopped (not replay it from the start)
        base.rng.bit_generator.state = state["scenario_rng"]
        base.episodes = state["episodes"]
        venv = PartialVecNormalize.load(str(ckpt / "vecnormalize.pkl"), base)
        model = PPO.load(ckpt / "model.zip", env=venv, device="cpu")
    else:
        if out.exists() and any(out.iterdir()):
            if not ((out / "checkpoints").exists() or (out / "best").exists() or (out / "summary.json").exists()):
                raise FileExistsError(f"out={str(out)!r}: not empty and not a training run's folder; refusing to "
                                      "overwrite it")
            shutil.rmtree(out)
        venv = PartialVecNormalize(base, norm_obs=normalize, norm_reward=norm_reward, gamma=hp.get("gamma", 0.99))
        model = PPO(policy_class, venv, seed=args.seed, device="cpu", verbose=args.verbose, **hp)
        state = {"best_score": -np.inf, "best_step": 0, "history": [], "wall_s": 0.0}
    jobs = validation_jobs(args)
    record = {"args": asdict(args), "hyperparams": load_block(args.hyperparams, ENV_ID, args.hp),
              "env": "anchor_set", "algo": "ppo", "distribution": asdict(dist)}
    started = time.perf_counter() - state["wall_s"]

    def checkpoint():
        state["wall_s"] = time.perf_counter() - started
        state["scenario_rng"], state["episodes"] = base.rng.bit_generator.state, base.episodes
        _save(model, venv, ckpt, record)
        state_path.write_text(json.dumps(state, indent=2))

    def evaluate_now():
        policy = AnchorSetPolicy(model.policy, venv.obs_rms if normalize else None, venv.clip_obs)
        score = validation_score(policy, jobs)
        state["history"].append({"step": int(model.num_timesteps), "val_return": score,
                                 "wall_s": time.perf_counter() - started})
        if score > state["best_score"]:
            state["best_score"], state["best_step"] = score, int(model.num_timesteps)
            _save(model, venv, out / "best", {**record, "val_return": score, "step": int(model.num_timesteps)})
        checkpoint()

    class Every(BaseCallback):
        def __init__(self):
            super().__init__()
            self.next_eval = (model.num_timesteps // args.eval_every_steps + 1) * args.eval_every_steps
            self.next_ckpt = (model.num_timesteps // args.checkpoint_every_steps + 1) * args.checkpoint_every_steps

        def _on_step(self) -> bool:
            if self.num_timesteps >= self.next_eval:
                self.next_eval += args.eval_every_steps
                evaluate_now()  # also checkpoints
            elif self.num_timesteps >= self.next_ckpt:
                self.next_ckpt += args.checkpoint_every_steps
                checkpoint()
            return not (args.max_wall_s and time.perf_counter() - started > args.max_wall_s)

    remaining = max(args.total_timesteps - model.num_timesteps, 0)
    if not resumed:
        # the untrained policy is the base rule itself: a candidate like any checkpoint, so a
        # training that never beats its base on validation ships the base, and says so
        evaluate_now()
    if remaining:
        model.learn(remaining, callback=Every(), reset_num_timesteps=not resumed)
    evaluate_now()
    wall = time.perf_counter() - started
    summary = {"seed": args.seed, "steps": int(model.num_timesteps), "wall_s": wall,
               "best_val_return": state["best_score"], "best_step": state["best_step"],
               "history": state["history"]}
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    venv.close()
    return summary


def add_arguments(p: argparse.ArgumentParser) -> None:
    d = Args()
    for f in dataclasses.fields(Args):
        flag = "--" + f.name.replace("_", "-")
        if f.name == "hp":
            p.add_argument(flag, action="append", default=[], help="hyperparameter override key=value (repeatable)")
        elif f.type == "bool":
            p.add_argument(flag, action=argparse.BooleanOptionalAction, default=getattr(d, f.name))
        elif f.name == "max_wall_s":
            p.add_argument(flag, type=float, default=d.max_wall_s, help="wall-clock budget, s")
        elif f.name == "val_max_cycles":
            p.add_argument(flag, type=int, default=None)
        else:
            p.add_argument(flag, type=type(getattr(d, f.name)), default=getattr(d, f.name))


def args_from_namespace(ns: argparse.Namespace) -> Args:
    names = {f.name for f in dataclasses.fields(Args)}
    return Args(**{k: v for k, v in vars(ns).items() if k in names})


def report(summary: dict) -> str:
    return json.dumps({k: v for k, v in summary.items() if k != "history"}, indent=2)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_arguments(parser)
    print(report(main(args_from_namespace(parser.parse_args()))))
