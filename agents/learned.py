"""A trained SB3 model behind the policy hook, so the harness compares it with the baselines.

``LearnedPolicy.load("runs/train/model.zip")`` reads the run record (``run.json``) and the
observation statistics (``vecnormalize.pkl``) saved beside the model by ``training.train``:
a ``scheduler`` model sees all anchors' features concatenated and decides for the team; a
``parallel`` model is applied to each anchor's own observation (shared policy).
"""

from __future__ import annotations

import json
import pickle
from pathlib import Path

import numpy as np


class LearnedPolicy:
    uses_ground_truth = False

    def __init__(self, model, kind: str, obs_normalizer=None, deterministic: bool = True):
        if kind not in ("scheduler", "parallel"):
            raise ValueError(f"kind={kind!r}: must be 'scheduler' or 'parallel'")
        self.model, self.kind, self.normalizer, self.deterministic = model, kind, obs_normalizer, deterministic

    @classmethod
    def load(cls, path: str | Path, deterministic: bool = True) -> LearnedPolicy:
        try:
            import stable_baselines3 as sb3
        except ImportError as err:  # the core installs without the train extra
            raise ImportError("LearnedPolicy needs stable-baselines3: pip install 'uwb-env[train]'") from err
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"model path={str(path)!r}: no such file")
        record_path = path.with_name("run.json")
        record = json.loads(record_path.read_text()) if record_path.exists() else {"algo": "ppo", "env": "scheduler"}
        algo = {"ppo": sb3.PPO, "a2c": sb3.A2C, "dqn": sb3.DQN}[record["algo"]]
        model = algo.load(str(path), device="cpu")
        stats = path.with_name("vecnormalize.pkl")
        normalizer = None
        if stats.exists():
            with open(stats, "rb") as f:
                normalizer = pickle.load(f)  # a VecNormalize without its venv: normalize_obs works
        kind = "scheduler" if record["env"] == "batched" else record["env"]  # same observations
        return cls(model, kind, normalizer, deterministic)

    def reset(self, seed: int | None = None) -> None:
        pass

    def incompatibility(self, config) -> str | None:
        """Why this model cannot act in an env built from ``config`` (an ``EnvConfig``), or None."""
        from uwb_env.system import OBS_FIELDS

        per_anchor = config.sim.dim + len(OBS_FIELDS)
        wanted = (config.sim.n_anchors * per_anchor,) if self.kind == "scheduler" else (per_anchor,)
        expected = tuple(self.model.observation_space.shape)
        return None if wanted == expected else _shape_mismatch("the env's observations", wanted, expected)

    def _predict(self, obs: np.ndarray) -> np.ndarray:
        expected = self.model.observation_space.shape
        if obs.shape[1:] != expected:
            raise ValueError(_shape_mismatch("observation", obs.shape[1:], expected))
        if self.normalizer is not None:
            obs = self.normalizer.normalize_obs(obs)
        action, _ = self.model.predict(obs, deterministic=self.deterministic)
        return np.asarray(action)

    def act(self, observations: dict[str, np.ndarray], infos: dict[str, dict]) -> dict[str, int]:
        agents = list(observations)
        if self.kind == "scheduler":
            decision = int(self._predict(np.concatenate([observations[a] for a in agents])[None])[0])
            return {a: decision for a in agents}
        actions = self._predict(np.stack([observations[a] for a in agents]))
        return {a: int(x) for a, x in zip(agents, actions, strict=True)}


def _shape_mismatch(what: str, got: tuple, expected: tuple) -> str:
    return (f"{what} shape {got} does not match the model's {expected}: it was trained for another number of "
            "anchors (or another env)")
