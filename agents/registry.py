"""Policies by name: ``"fixed:10"``, ``"threshold:0.15"``, ``"learned:model.zip"``, ...

A *spec* is ``name`` or ``name:parameter``; the evaluation harness, the CLI and the sweeps
all build policies from specs so that a result row names exactly what ran.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

from uwb_env.agents.baselines import (
    AlwaysPolicy,
    FixedIntervalPolicy,
    NeverPolicy,
    OraclePolicy,
    RandomPolicy,
    ResidualTriggerPolicy,
    UncertaintyThresholdPolicy,
)

SHIPPED_MODELS = Path(__file__).with_name("models")


def shipped_model(name: str) -> Path:
    """A model shipped with the package: ``learned:ppo_scheduler`` -> agents/models/ppo_scheduler/model.zip."""
    return SHIPPED_MODELS / name / "model.zip"


def _learned(param: str, dt_s: float):
    """``learned:<model>`` or, for the per-anchor residual scheduler, ``learned:<model>@<threshold_m>``
    (the base rule's threshold on the predicted std; default ``anchor_set.DEFAULT_BASE_THRESHOLD_M``)
    or ``learned:<model>@drift:<threshold_m>`` (the base rule on the drift since calibration) or
    ``learned:<model>@team:<threshold_m>`` (the team threshold rule: a team round when any
    anchor's predicted std passes it)."""
    from uwb_env.agents.learned import LearnedPolicy

    path, threshold, measure = param, "", "total"
    head, at, tail = param.rpartition("@")
    # '@' followed by more path (a directory named with '@') is part of the model's path
    if at and "/" not in tail and not tail.endswith(".zip"):
        path, threshold = head, tail
        if threshold.startswith(("drift:", "total:", "team:")):  # the base rule's measure (default: total)
            measure, _, threshold = threshold.partition(":")
        if not threshold:
            raise ValueError(f"learned:{param}: '@' needs a base threshold in metres, e.g. learned:anchor_set@0.3")
        try:
            float(threshold)
        except ValueError:
            raise ValueError(f"learned:{param}: the base threshold after '@' must be a number in metres, "
                             f"got {threshold!r}") from None
    if "/" not in path and not path.endswith((".zip", ".npz")):  # a shipped model's name
        path = str(shipped_model(path))
    record = Path(path).with_name("run.json")
    run = json.loads(record.read_text()) if record.is_file() else {}
    if run.get("env") == "distilled":  # training.train_distilled: the rule plus predicted departures
        from uwb_env.agents.distilled import DistilledPolicy, parse_base

        if not threshold:  # the rule it was distilled over
            measure, value = parse_base(run["base"])
        else:
            value = float(threshold)
        policy = DistilledPolicy.load(path, base_threshold_m=value, base_measure=measure)
        policy.dt_s = dt_s
        return policy
    if run.get("env") == "anchor_set":
        from uwb_env.agents.anchor_set import AnchorSetPolicy

        kwargs = {"base_threshold_m": float(threshold), "base_measure": measure} if threshold else {}
        policy = AnchorSetPolicy.load(path, **kwargs)  # any team size; per_anchor actions
        policy.dt_s = dt_s
        return policy
    if threshold:
        raise ValueError(f"learned:{param}: only the per-anchor scheduler (training.train_anchor_set) takes "
                         "'@<base threshold>'")
    return LearnedPolicy.load(path)


def _lookahead(param: str | None, clairvoyant: bool):
    """``lookahead``, ``lookahead:H`` or ``lookahead:H@K`` (horizon H steps, base interval K steps)."""
    from uwb_env.agents.lookahead import ClairvoyantPolicy, LookaheadPolicy

    horizon, _, base = (param or "").partition("@")
    kwargs = {}
    if horizon:
        kwargs["horizon_steps"] = int(horizon)
    if base:
        kwargs["base_interval_steps"] = int(base)
    return (ClairvoyantPolicy if clairvoyant else LookaheadPolicy)(**kwargs)


def _rollout(param: str | None, dt_s: float):
    """``rollout:H@BASE``: horizon H steps over the base scheduler spec BASE."""
    from uwb_env.agents.lookahead import RolloutPolicy

    horizon, at, base = (param or "").partition("@")
    if not at or not base:
        raise ValueError("rollout needs a base scheduler: rollout:H@BASE, e.g. rollout:60@per_anchor_drift:0.2")
    return RolloutPolicy(base, horizon_steps=int(horizon) if horizon else 60, dt_s=dt_s)


def _rllib(path: str, dt_s: float):
    from uwb_env.agents.learned_rllib import RLlibPolicy

    # Ray restores checkpoints from URIs: a relative path has no scheme ("URI has empty scheme")
    return RLlibPolicy.load(str(Path(path).expanduser().resolve()))


# name -> (factory(parameter string or None, dt_s), parameter meaning)
POLICIES: dict[str, tuple[Callable, str]] = {
    "fixed": (lambda p, dt: FixedIntervalPolicy(interval_steps=int(p or 10)), "interval in steps (default 10)"),
    "fixed_s": (lambda p, dt: FixedIntervalPolicy(interval_steps=None, interval_s=float(p or 2.0), dt_s=dt),
                "interval in seconds"),
    "threshold": (lambda p, dt: UncertaintyThresholdPolicy(float(p or 0.15)), "predicted anchor std threshold (m)"),
    "residual": (lambda p, dt: ResidualTriggerPolicy(float(p or 0.2)), "tag-fix RMS residual threshold (m)"),
    "never": (lambda p, dt: NeverPolicy(), "-"),
    "always": (lambda p, dt: AlwaysPolicy(), "-"),
    "random": (lambda p, dt: RandomPolicy(float(p or 0.05)), "request probability per step"),
    "per_anchor_threshold": (lambda p, dt: _per_anchor_threshold(p), "per-anchor predicted std threshold (m); "
                             "needs action_mode=per_anchor"),
    "per_anchor_drift": (lambda p, dt: _per_anchor_threshold(p, "drift"), "per-anchor threshold (m) on the drift "
                         "since the anchor's last calibration; needs action_mode=per_anchor"),
    "oracle": (lambda p, dt: OraclePolicy(float(p or 0.3)), "true mean anchor error threshold (m); GROUND TRUTH"),
    "lookahead": (lambda p, dt: _lookahead(p, False), "H[@K]: planner over sampled futures, horizon H steps "
                  "(default 30), base fixed interval K (default 10); GROUND TRUTH"),
    "rollout": (lambda p, dt: _rollout(p, dt), "H@BASE: one step of policy improvement over the scheduler BASE "
                "(e.g. the tuned best heuristic), horizon H steps; GROUND TRUTH"),
    "clairvoyant": (lambda p, dt: _lookahead(p, True), "H[@K]: the lookahead on the real future's noise; "
                    "GROUND TRUTH, optimistic bound"),
    "learned": (lambda p, dt: _learned(p, dt), "path of a saved SB3 model (.zip), or a shipped model's name; "
                "@T / @drift:T / @team:T: the per-anchor scheduler's base rule and threshold (m)"),
    "rllib": (lambda p, dt: _rllib(p, dt), "path of an RLlib checkpoint folder"),
}


class PolicySpecError(ValueError):
    """A policy spec that names no known policy or carries a bad parameter."""


def _per_anchor_threshold(param, measure: str = "total"):
    from uwb_env.agents.per_anchor import PerAnchorThresholdPolicy

    return PerAnchorThresholdPolicy(float(param or 0.15), measure=measure)


def make_policy(spec: str, dt_s: float = 0.2):
    """Build the policy named by ``spec`` (see the module docstring)."""
    name, _, param = spec.partition(":")
    if name not in POLICIES:
        raise PolicySpecError(f"policy={spec!r}: unknown name {name!r}; known: {', '.join(POLICIES)}")
    if name in ("learned", "rllib") and not param:
        raise PolicySpecError(f"policy={spec!r}: {name!r} needs a model path, e.g. learned:model.zip")
    if name == "rollout" and "@" not in param:
        raise PolicySpecError(f"policy={spec!r}: rollout needs a base scheduler: rollout:H@BASE, "
                              "e.g. rollout:60@per_anchor_drift:0.2")
    try:
        return POLICIES[name][0](param or None, dt_s)
    except (TypeError, ValueError) as err:
        raise PolicySpecError(f"policy={spec!r}: {err}") from err
