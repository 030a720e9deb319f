"""The per_anchor action mode: one anchor re-locates against the others."""

import numpy as np
from uwb_env.agents.per_anchor import PerAnchorThresholdPolicy
from uwb_env.agents.registry import make_policy

from uwb_env import parallel_env
from uwb_env.env.policy import rollout


def test_relocate_me_runs_a_short_round_that_fixes_only_that_anchor():
    env = parallel_env(action_mode="per_anchor", max_cycles=400)
    obs, infos = env.reset(seed=3)
    assert env.action_space("anchor_0").n == 3
    idle = {a: 0 for a in env.agents}
    for _ in range(150):  # let odometry drift
        obs, _, _, _, infos = env.step(idle)
    var_before = env.system.predicted_anchor_var_m2().copy()
    actions = dict(idle, anchor_2=1)
    obs, _, _, _, infos = env.step(actions)
    assert infos["anchor_0"]["round_anchor"] == 2 and infos["anchor_0"]["round_started"]
    steps = 1
    while infos["anchor_0"]["calibrating"]:
        obs, _, _, _, infos = env.step(idle)
        steps += 1
    assert not infos["anchor_0"]["calibration_failed"] and env.calibration_error == ""
    assert infos["anchor_0"]["anchor_round_count"] == 1 and infos["anchor_0"]["calibration_count"] == 1
    var = env.system.predicted_anchor_var_m2()
    assert var[2] < var_before[2] and var[0] >= var_before[0]  # only anchor 2 was refreshed
    # 1/n of a team round: the 4-anchor team round at K=5 takes 5 steps of 0.2 s, this one ~1-2
    assert steps <= 3


def test_relocation_reduces_the_anchors_error_over_seeds():
    """Relative to the others (the aligned frame: one anchor cannot fix the team's common drift)."""
    before, after = [], []
    for seed in range(8):
        env = parallel_env(action_mode="per_anchor", max_cycles=400)
        env.reset(seed=seed)
        idle = {a: 0 for a in env.agents}
        for _ in range(300):
            env.step(idle)
        before.append(env.system.anchor_errors_m()[2])
        _, _, _, _, infos = env.step(dict(idle, anchor_2=1))
        while infos["anchor_0"]["calibrating"]:
            _, _, _, _, infos = env.step(idle)
        after.append(env.system.anchor_errors_m()[2])
    assert sum(after) < 0.7 * sum(before), (before, after)


def test_a_team_request_wins_over_relocation_requests():
    env = parallel_env(action_mode="per_anchor")
    env.reset(seed=0)
    actions = {a: 1 for a in env.agents}
    actions["anchor_0"] = 2  # trigger "any"
    _, _, _, _, infos = env.step(actions)
    assert infos["anchor_0"]["round_started"] and infos["anchor_0"]["round_anchor"] == -1


def test_per_anchor_threshold_heuristic_runs_episodes():
    policy = make_policy("per_anchor_threshold:0.1")
    assert isinstance(policy, PerAnchorThresholdPolicy)
    result = rollout(parallel_env(action_mode="per_anchor", max_cycles=200), policy, seed=1)
    assert np.isfinite(result.tag_error_m).all() and result.calibrating.mean() > 0
