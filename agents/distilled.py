"""A deployable scheduler distilled from the ground-truth rollout reference.

The rollout reference (``agents/lookahead.py``, ``rollout:H@BASE``) improves on a tuned
per-anchor rule by departing from it where simulated futures on the *true* state say a
departure pays: a team round now, or holding off until the next decision. It reads ground
truth, so it cannot be deployed. :class:`DistilledPolicy` keeps the rule and learns *where* to
depart from what a deployment can see: every ``decide_every_steps`` (no round running) a
:class:`GainModel` predicts, from the anchors' observed uncertainty, residuals and the rule's
own action, the reward the two departures would gain over the rule in the next
``horizon_steps`` (the rollout's measured gains are its regression targets,
``training/train_distilled.py``), and the policy departs when a predicted gain exceeds
``margin`` (chosen on validation seeds). With no departure it acts exactly as the rule.

Team features (``TEAM_FEATURES``, any team size): over the anchors, the mean, max and min of
each anchor's time since calibration, predicted std, calibration std, last calibration RMS,
tag-fix RMS, own range residual, drift since calibration (sqrt(predicted^2 - calibration^2)),
and the drift and the predicted std over the rule's threshold; the share of anchors the rule
gives each action (nothing, re-locate, team round); team size, step length, the threshold, and
the share of the gain horizon left before the episode ends (``max_cycles`` minus the number of
the decision's act call, as the rollout counts it when its data are recorded).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from uwb_env.agents.per_anchor import TEAM_ROUND, check_measure, threshold_actions

from uwb_env.system import OBS_FIELDS

_PER_ANCHOR = ("time_since_calibration_s", "predicted_position_std_m", "calibration_position_std_m",
               "last_calibration_rms_residual_m", "tag_fix_rms_residual_m", "own_range_residual_m",
               "drift_m", "drift_over_threshold", "predicted_over_threshold")
TEAM_FEATURES = (
    tuple(f"{stat}_{name}" for stat in ("mean", "max", "min") for name in _PER_ANCHOR)
    + ("base_share_nothing", "base_share_relocate", "base_share_team", "n_anchors", "dt_s", "base_threshold_m",
       "horizon_left")
)
MOVES = ("team", "wait")  # the departures, in the order of the model's outputs
_FIELD = {name: i for i, name in enumerate(OBS_FIELDS)}


def team_features(own: np.ndarray, base_actions: np.ndarray, threshold_m: float, dt_s: float,
                  steps_left: int, horizon_steps: int) -> np.ndarray:
    """(N, len(OBS_FIELDS)) per-anchor observation fields (positions dropped), the rule's (N,)
    actions -> (len(TEAM_FEATURES),) float64."""
    own = np.asarray(own, dtype=np.float64)
    pred, cal = own[:, _FIELD["predicted_position_std_m"]], own[:, _FIELD["calibration_position_std_m"]]
    drift = np.sqrt(np.maximum(pred * pred - cal * cal, 0.0))
    per = np.column_stack([own[:, _FIELD[f]] for f in _PER_ANCHOR[:6]] + [drift, drift / threshold_m,
                                                                         pred / threshold_m])
    base = np.asarray(base_actions)
    share = [float((base == k).mean()) for k in range(3)]
    left = min(max(steps_left, 0), horizon_steps) / horizon_steps
    return np.concatenate([per.mean(0), per.max(0), per.min(0),
                           share + [float(len(base)), float(dt_s), float(threshold_m), left]])


def parse_base(base: str) -> tuple[str, float]:
    """``drift:0.21`` -> ("drift", 0.21); ``0.3`` -> ("total", 0.3); ``team:1`` -> ("team", 1.0)."""
    measure, _, value = base.rpartition(":")
    return measure or "total", float(value)


def base_spec(base: str) -> str:
    """The heuristic spec of a base rule: ``drift:0.21`` -> ``per_anchor_drift:0.21``."""
    measure, value = parse_base(base)
    return {"total": "per_anchor_threshold", "drift": "per_anchor_drift", "team": "threshold"}[measure] + f":{value:g}"


@dataclass(frozen=True)
class GainModel:
    """A small MLP (tanh hidden layers) on standardized team features -> the predicted gain of
    each departure (``MOVES``) over the rule, in summed reward over the horizon. Numpy only: a
    deployment needs no torch. ``weights``: [(W, b), ...]; ``mean``/``scale`` standardize the input."""

    mean: np.ndarray
    scale: np.ndarray
    weights: tuple
    horizon_steps: int
    decide_every_steps: int

    def __post_init__(self):
        for name in ("horizon_steps", "decide_every_steps"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name}={getattr(self, name)!r}: must be an integer >= 1")
        width = len(TEAM_FEATURES)
        if np.shape(self.mean) != (width,) or np.shape(self.scale) != (width,):
            raise ValueError(f"mean/scale: shapes {np.shape(self.mean)}, {np.shape(self.scale)}; the team features "
                             f"need ({width},)")
        for i, (w, b) in enumerate(self.weights):
            if np.ndim(w) != 2 or np.shape(w)[0] != width or np.shape(b) != (np.shape(w)[1],):
                raise ValueError(f"weights[{i}]: shapes {np.shape(w)}, {np.shape(b)} do not chain from {width} inputs")
            width = np.shape(w)[1]
        if width != len(MOVES):
            raise ValueError(f"weights: {width} outputs, the model predicts one gain per move {MOVES}")

    def evaluate(self, features: np.ndarray) -> np.ndarray:
        h = (np.asarray(features, dtype=np.float64) - self.mean) / self.scale
        for i, (w, b) in enumerate(self.weights):
            h = h @ w + b
            if i < len(self.weights) - 1:
                h = np.tanh(h)
        return h

    def save(self, path: str | Path) -> None:
        path = Path(path)
        arrays = {"mean": self.mean, "scale": self.scale}
        for i, (w, b) in enumerate(self.weights):
            arrays[f"w{i}"], arrays[f"b{i}"] = w, b
        np.savez(path, **arrays)
        path.with_suffix(".json").write_text(json.dumps({
            "kind": "distilled_gain_model", "features": list(TEAM_FEATURES), "moves": list(MOVES),
            "layers": len(self.weights), "horizon_steps": self.horizon_steps,
            "decide_every_steps": self.decide_every_steps}, indent=1))

    @classmethod
    def load(cls, path: str | Path) -> GainModel:
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"model path={str(path)!r}: no such file")
        meta_path = path.with_suffix(".json")
        if not meta_path.is_file():
            raise FileNotFoundError(f"model path={str(path)!r}: no {meta_path.name} beside it (saved with the model)")
        meta = json.loads(meta_path.read_text())
        if meta.get("kind") != "distilled_gain_model" or tuple(meta.get("features", ())) != TEAM_FEATURES:
            raise ValueError(f"model path={str(path)!r}: not a gain model on this version's team features")
        with np.load(path) as z:
            weights = tuple((z[f"w{i}"], z[f"b{i}"]) for i in range(int(meta["layers"])))
            return cls(z["mean"], z["scale"], weights, int(meta["horizon_steps"]), int(meta["decide_every_steps"]))


class DistilledPolicy:
    """The per-anchor rule (``base_measure`` at ``base_threshold_m``, as
    ``per_anchor_threshold`` / ``per_anchor_drift``) with the departures a :class:`GainModel`
    predicts to gain more than ``margin`` (see the module docstring). Spec:
    ``learned:<dir>/model.npz@drift:<threshold>`` (the run record beside it says what it is)."""

    uses_ground_truth = False
    action_mode = "per_anchor"

    def __init__(self, model: GainModel, margin: float, base_threshold_m: float, base_measure: str = "drift",
                 dt_s: float = 0.2, max_cycles: int = 500):
        if not (np.isfinite(base_threshold_m) and base_threshold_m > 0):
            raise ValueError(f"base_threshold_m={base_threshold_m!r}: must be finite and > 0")
        if margin != margin or margin == -np.inf:
            raise ValueError(f"margin={margin!r}: must be a number or +inf (never depart)")
        self.model, self.margin = model, float(margin)
        self.base_threshold_m, self.base_measure = float(base_threshold_m), check_measure(base_measure)
        self.dt_s, self.max_cycles = float(dt_s), int(max_cycles)
        self.reset()

    @classmethod
    def load(cls, path, base_threshold_m: float, base_measure: str = "drift", margin: float | None = None):
        path = Path(path)
        model = GainModel.load(path)
        record = path.with_name("run.json")
        if margin is None:
            if not record.is_file():
                raise ValueError(f"model path={str(path)!r}: no margin given and no {record.name} beside it")
            run = json.loads(record.read_text())
            if "margin" not in run:
                raise ValueError(f"{record}: no 'margin' (not written by training.train_distilled?)")
            chosen = run["margin"]
            margin = np.inf if chosen is None else float(chosen)  # None: validation chose the rule itself
        return cls(model, margin, base_threshold_m, base_measure)

    def configure(self, config) -> None:
        self.dt_s, self.max_cycles = float(config.sim.dt_s), int(config.max_cycles)

    def incompatibility(self, config) -> str | None:
        return None  # any team size, 2D or 3D

    def reset(self, seed: int | None = None) -> None:
        self.t = 0
        self._hold = 0
        self.decisions = {"base": 0, "team": 0, "wait": 0}
        self.last_gains = np.full(len(MOVES), np.nan)

    def act(self, observations, infos) -> dict[str, int]:
        agents = list(observations)
        own = np.stack([np.asarray(observations[a])[-len(OBS_FIELDS):] for a in agents])
        pred, cal = own[:, _FIELD["predicted_position_std_m"]], own[:, _FIELD["calibration_position_std_m"]]
        base = threshold_actions(pred, cal, self.base_threshold_m, measure=self.base_measure)
        self.t += 1
        if own[0, _FIELD["calibrating"]] > 0.5:  # requests are ignored while a round runs
            return {a: int(x) for a, x in zip(agents, base, strict=True)}
        if self._hold > 0:
            self._hold -= 1
            return {a: 0 for a in agents}
        if self.t % self.model.decide_every_steps:
            return {a: int(x) for a, x in zip(agents, base, strict=True)}
        features = team_features(own, base, self.base_threshold_m, self.dt_s, self.max_cycles - self.t,
                                 self.model.horizon_steps)
        gains = self.model.evaluate(features)
        self.last_gains = gains
        # the rule already asks for a team round: that departure is no departure
        if (base == TEAM_ROUND).all():
            gains = gains.copy()
            gains[MOVES.index("team")] = -np.inf
        k = int(np.argmax(gains))
        if not gains[k] > self.margin:
            self.decisions["base"] += 1
            return {a: int(x) for a, x in zip(agents, base, strict=True)}
        self.decisions[MOVES[k]] += 1
        if MOVES[k] == "wait":
            self._hold = self.model.decide_every_steps - 1
            return {a: 0 for a in agents}
        return {a: TEAM_ROUND for a in agents}
