"""The lookahead reference: flagged as ground truth, and never sees the real future."""

import copy

import numpy as np
import pytest
from uwb_env.agents.lookahead import ClairvoyantPolicy, LookaheadPolicy
from uwb_env.agents.registry import make_policy
from uwb_env.training.evaluate import format_table, summarize

from uwb_env.env.parallel_env import UWBCalibrationParallelEnv
from uwb_env.env.policy import rollout

SMALL = dict(horizon_steps=8, n_futures=2, base_interval_steps=6, decide_every_steps=2)


class _Recorder:
    uses_ground_truth = True

    def __init__(self, inner):
        self.inner, self.actions = inner, []

    def bind(self, env):
        self.inner.bind(env)

    def reset(self, seed=None):
        self.inner.reset(seed)

    def act(self, obs, infos):
        actions = self.inner.act(obs, infos)
        self.actions.append(actions)
        return actions


class _Replay:
    uses_ground_truth = False

    def __init__(self, actions):
        self.actions = actions

    def reset(self, seed=None):
        self.t = 0

    def act(self, obs, infos):
        self.t += 1
        return self.actions[self.t - 1]


def test_specs_build_ground_truth_policies():
    for spec in ("lookahead", "lookahead:12", "lookahead:12@8", "clairvoyant:5"):
        policy = make_policy(spec)
        assert policy.uses_ground_truth is True
    assert make_policy("lookahead:12@8").base_interval_steps == 8
    assert make_policy("clairvoyant").clairvoyant and make_policy("clairvoyant").n_futures == 1
    with pytest.raises(ValueError):
        make_policy("lookahead:0")
    metrics = ("mean_tag_error_m", "median_tag_error_m", "p95_tag_error_m", "mean_anchor_error_m",
               "calibrations_per_min", "fraction_calibrating", "return")
    episodes = [{"policy": "lookahead:12", "seed": s, "uses_ground_truth": True, **{m: 0.1 + s for m in metrics}}
                for s in range(3)]
    rows = summarize(episodes, ["lookahead:12"], ["lookahead:12"])
    assert "lookahead:12 (GT)" in format_table(rows)


def test_planning_leaves_the_real_trajectory_untouched():
    env = UWBCalibrationParallelEnv(max_cycles=40)
    planner = _Recorder(LookaheadPolicy(**SMALL))
    planner.bind(env)
    planned = rollout(env, planner, seed=7)
    assert planner.inner.simulated_steps > 0
    assert any(a["anchor_0"] for a in planner.actions)
    # The same actions without any simulation in between give the same episode, bit for bit.
    replayed = rollout(UWBCalibrationParallelEnv(max_cycles=40), _Replay(planner.actions), seed=7)
    np.testing.assert_array_equal(planned.reward, replayed.reward)
    np.testing.assert_array_equal(planned.tag_error_m, replayed.tag_error_m)


def _decision_state():
    env = UWBCalibrationParallelEnv(max_cycles=60)
    env.reset(seed=3)
    for t in range(15):
        env.step({a: int(t == 2) for a in env.agents})
    # The same true state with another future: the real generator replaced by a different one.
    other = copy.deepcopy(env, {id(env.np_random): np.random.default_rng(987654)})
    assert other.system.world.rng is other.np_random is not env.np_random
    return env, other


def test_decisions_do_not_depend_on_the_real_future():
    env, other = _decision_state()
    state = env.np_random.bit_generator.state
    gains = []
    for e in (env, other):
        planner = LookaheadPolicy(**SMALL)
        planner.reset(seed=1)
        planner.bind(e)
        planner._plan(e)
        gains.append(planner.last_gain)
    assert gains[0] == gains[1] and np.isfinite(gains[0])
    assert env.np_random.bit_generator.state == state  # never read-advanced


def test_clairvoyant_does_read_the_real_future():
    env, other = _decision_state()
    gains = []
    for e in (env, other):
        planner = ClairvoyantPolicy(**SMALL)
        planner.reset(seed=1)
        planner.bind(e)
        planner._plan(e)
        gains.append(planner.last_gain)
    assert gains[0] != gains[1]  # the sensitivity the fair planner must not have


def test_needs_a_bound_simulated_env():
    planner = LookaheadPolicy(**SMALL)
    planner.reset(0)
    with pytest.raises(RuntimeError, match="bind"):
        planner.act({"anchor_0": np.zeros(10)}, {})
