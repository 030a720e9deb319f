"""Heuristics for the ``per_anchor`` action mode (0 nothing, 1 re-locate me, 2 team round).

They get the same actions as a learned per-anchor scheduler, so comparisons stay fair.
"""

from __future__ import annotations

import numpy as np

from uwb_env.agents.baselines import _FROM_END, _positive

NOTHING, RELOCATE_ME, TEAM_ROUND = 0, 1, 2


MEASURES = ("total", "drift", "team")
# the per-anchor heuristics' spec names -> the measure their rule compares
FAMILIES = {"per_anchor_threshold": "total", "per_anchor_drift": "drift"}
# the tuned families the learned residual can take as its base rule: the per-anchor ones and
# the team uncertainty threshold (``threshold:T``, baselines.UncertaintyThresholdPolicy: every
# anchor votes for a team round when any predicted std passes T)
BASE_FAMILIES = {**FAMILIES, "threshold": "team"}


def check_measure(measure: str) -> str:
    if measure not in MEASURES:
        raise ValueError(f"measure={measure!r}: must be one of {MEASURES}")
    return measure


def learned_base(spec: str) -> str:
    """A base family's tuned spec -> the learned residual's base on the same rule (the part
    after ``@`` in ``learned:<model>@...``): ``per_anchor_threshold:T`` -> ``T``,
    ``per_anchor_drift:T`` -> ``drift:T``, ``threshold:T`` -> ``team:T``."""
    family, _, value = spec.partition(":")
    if family not in BASE_FAMILIES:
        raise ValueError(f"spec={spec!r}: not a rule the learned residual can take as its base "
                         f"({', '.join(BASE_FAMILIES)})")
    return value if BASE_FAMILIES[family] == "total" else f"{BASE_FAMILIES[family]}:{value}"


def threshold_actions(predicted_std_m, calibration_std_m, threshold_m, team_fraction: float = 0.5,
                      measure: str = "total") -> np.ndarray:
    """The per-anchor threshold rule on (..., N) predicted and last-calibration stds
    (``threshold_m`` a float, or one per team of shape (...)): -> (..., N) actions. One
    implementation for the heuristics and for the base of the learned residual scheduler
    (agents/anchor_set.py).

    ``measure`` says what must exceed the threshold for an anchor to be stale:

    - ``"total"``: its predicted std (``per_anchor_threshold``), compared in the stds' own dtype
      (float32 observations: NumPy's scalar promotion);
    - ``"drift"``: the drift since its last calibration, sqrt(predicted^2 - calibration^2), in
      float64 (``per_anchor_drift``): what a new calibration would take away. On the total, an
      anchor whose calibration alone is above the threshold asks again right after every
      round: in 3D, an anchor off the plane of near-coplanar others has a height its ranges
      barely fix, and the total rule re-located it back to back, each round holding every
      tag's fix (``three_d`` test seed 1000011: 119 steps of rounds, > 1 m of mean tag error).
      When a calibration is poor by chance (fast robots: rounds fit poorly), the total rule's
      early repeat pays instead; which rule fits a deployment is tuned like the threshold;
    - ``"team"``: the team uncertainty threshold (``threshold:T``): when any anchor's predicted
      std passes T, every anchor asks for a team round (no single re-locations).
    """
    check_measure(measure)
    thr = float(threshold_m) if np.ndim(threshold_m) == 0 else np.asarray(threshold_m, dtype=np.float64)[..., None]
    if measure == "team":  # threshold:T: any anchor past T, and the whole team asks for a round
        pred = np.asarray(predicted_std_m)
        stale = np.broadcast_to((pred > thr).any(-1, keepdims=True), pred.shape)
        return np.where(stale, TEAM_ROUND, NOTHING)
    if measure == "total":
        pred = np.asarray(predicted_std_m)
        stale = pred > thr
    else:
        pred = np.asarray(predicted_std_m, dtype=np.float64)
        cal = np.asarray(calibration_std_m, dtype=np.float64)
        stale = pred * pred - cal * cal > thr * thr
    team = stale.sum(-1, keepdims=True) >= team_fraction * pred.shape[-1]
    return np.where(team, TEAM_ROUND, np.where(stale, RELOCATE_ME, NOTHING))


def team_vote(actions, team_fraction: float = 0.5) -> np.ndarray:
    """(..., N) per-anchor actions with the team-round requests counted as votes: a team round
    is asked for only when at least ``team_fraction`` of the team votes for it (the threshold
    rule's own quorum); a vote short of it is a "nothing". The env starts a team round on any
    request, which on 16 anchors lets one anchor's request take the channel for ~6 s."""
    actions = np.asarray(actions)
    quorum = (actions == TEAM_ROUND).sum(-1, keepdims=True) >= team_fraction * actions.shape[-1]
    return np.where((actions == TEAM_ROUND) & ~quorum, NOTHING, actions)


class PerAnchorThresholdPolicy:
    """Each anchor asks to re-locate itself when its own uncertainty exceeds ``threshold_m``
    (``measure``: its predicted std, or the drift since its last calibration; see
    :func:`threshold_actions`); when at least ``team_fraction`` of the anchors exceed it at once,
    they ask for a team round instead (one round re-estimates them all: cheaper than one by
    one). Specs: ``per_anchor_threshold:T`` (total), ``per_anchor_drift:T`` (drift)."""

    uses_ground_truth = False
    action_mode = "per_anchor"  # the evaluation harness runs it with these actions

    def __init__(self, threshold_m: float = 0.15, team_fraction: float = 0.5, measure: str = "total"):
        self.threshold_m = _positive("threshold_m", threshold_m)
        if not 0 < team_fraction <= 1:
            raise ValueError(f"team_fraction={team_fraction!r}: must be in (0, 1]")
        self.team_fraction = team_fraction
        self.measure = check_measure(measure)

    def reset(self, seed: int | None = None) -> None:
        pass

    def act(self, observations, infos):
        pred, cal = _FROM_END["predicted_position_std_m"], _FROM_END["calibration_position_std_m"]
        agents = list(observations)
        actions = threshold_actions([observations[a][pred] for a in agents], [observations[a][cal] for a in agents],
                                    self.threshold_m, self.team_fraction, self.measure)
        return {agent: int(x) for agent, x in zip(agents, actions, strict=True)}
