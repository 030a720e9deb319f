import numpy as np
import pytest
from uwb_env.agents import (
    AlwaysPolicy,
    FixedIntervalPolicy,
    NeverPolicy,
    OraclePolicy,
    RandomPolicy,
    ResidualTriggerPolicy,
    UncertaintyThresholdPolicy,
)

import uwb_env
from uwb_env.env import CalibrationPolicy, rollout


@pytest.mark.parametrize("policy", [FixedIntervalPolicy(10), UncertaintyThresholdPolicy(), ResidualTriggerPolicy(),
                                    NeverPolicy(), AlwaysPolicy(), RandomPolicy(0.1), OraclePolicy()])
def test_every_baseline_implements_the_hook(policy):
    assert isinstance(policy, CalibrationPolicy)
    res = rollout(uwb_env.parallel_env(max_cycles=60), policy, seed=0)
    assert res.steps == 60


def test_fixed_interval_calibrates_exactly_every_k_steps():
    res = rollout(uwb_env.parallel_env(max_cycles=200), FixedIntervalPolicy(interval_steps=25), seed=1)
    starts = np.flatnonzero(res.round_started) + 1  # 1-based step numbers
    np.testing.assert_array_equal(starts, np.arange(25, 201, 25))


def test_fixed_interval_in_seconds():
    assert FixedIntervalPolicy(interval_steps=None, interval_s=2.0, dt_s=0.2).interval_steps == 10
    with pytest.raises(ValueError):
        FixedIntervalPolicy(interval_steps=5, interval_s=1.0)


def test_never_and_always():
    never = rollout(uwb_env.parallel_env(max_cycles=100), NeverPolicy(), seed=0)
    always = rollout(uwb_env.parallel_env(max_cycles=100), AlwaysPolicy(), seed=0)
    assert never.round_started.sum() == 0
    # back-to-back rounds of 0.9 s, each started in the step after the previous one ended
    assert always.summary()["fraction_calibrating"] == pytest.approx(0.9, abs=0.03)
    assert never.summary()["fraction_calibrating"] == 0.0


def test_uncertainty_threshold_fires_when_predicted_std_crosses():
    env = uwb_env.parallel_env(max_cycles=300)
    policy = UncertaintyThresholdPolicy(threshold_m=0.1)
    obs, infos = env.reset(seed=3)
    fired_at = []
    for _ in range(300):
        predicted = max(o[-7] for o in obs.values())
        actions = policy.act(obs, infos)
        assert bool(actions["anchor_0"]) == (predicted > 0.1)
        obs, _, _, _, infos = env.step(actions)
        if infos["anchor_0"]["round_started"]:
            fired_at.append(predicted)
    assert fired_at and min(fired_at) > 0.1


def test_residual_trigger_fires_only_above_threshold():
    policy = ResidualTriggerPolicy(threshold_m=0.2)
    quiet = {f"anchor_{i}": np.zeros(10, np.float32) for i in range(4)}
    loud = {k: v.copy() for k, v in quiet.items()}
    loud["anchor_2"][-4] = 0.3  # tag_fix_rms_residual_m
    assert not any(policy.act(quiet, {}).values())
    assert all(policy.act(loud, {}).values())


def test_oracle_declares_and_uses_only_ground_truth():
    oracle = OraclePolicy(threshold_m=0.1)
    assert oracle.uses_ground_truth
    obs = {f"anchor_{i}": np.full(10, 99.0, np.float32) for i in range(4)}  # observations are ignored
    assert not any(oracle.act(obs, {"anchor_0": {"mean_anchor_error_m": 0.05}}).values())
    assert all(oracle.act(obs, {"anchor_0": {"mean_anchor_error_m": 0.2}}).values())
    assert not UncertaintyThresholdPolicy().uses_ground_truth


def test_random_policy_is_seeded():
    a = rollout(uwb_env.parallel_env(max_cycles=80), RandomPolicy(0.2), seed=4)
    b = rollout(uwb_env.parallel_env(max_cycles=80), RandomPolicy(0.2), seed=4)
    np.testing.assert_array_equal(a.round_started, b.round_started)
