"""Heuristics for the ``per_anchor`` action mode (0 nothing, 1 re-locate me, 2 team round).

They get the same actions as a learned per-anchor scheduler, so comparisons stay fair.
"""

from __future__ import annotations

from uwb_env.agents.baselines import _FROM_END, _positive

NOTHING, RELOCATE_ME, TEAM_ROUND = 0, 1, 2


class PerAnchorThresholdPolicy:
    """Each anchor asks to re-locate itself when its own predicted position std exceeds
    ``threshold_m``; when at least ``team_fraction`` of the anchors exceed it at once, they ask
    for a team round instead (one round re-estimates them all: cheaper than one by one)."""

    uses_ground_truth = False
    action_mode = "per_anchor"  # the evaluation harness runs it with these actions

    def __init__(self, threshold_m: float = 0.15, team_fraction: float = 0.5):
        self.threshold_m = _positive("threshold_m", threshold_m)
        if not 0 < team_fraction <= 1:
            raise ValueError(f"team_fraction={team_fraction!r}: must be in (0, 1]")
        self.team_fraction = team_fraction

    def reset(self, seed: int | None = None) -> None:
        pass

    def act(self, observations, infos):
        column = _FROM_END["predicted_position_std_m"]
        stale = {agent: bool(obs[column] > self.threshold_m) for agent, obs in observations.items()}
        if sum(stale.values()) >= self.team_fraction * len(stale):
            return {agent: TEAM_ROUND for agent in observations}
        return {agent: RELOCATE_ME if s else NOTHING for agent, s in stale.items()}
