import pickle

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from pettingzoo.test import api_test, max_cycles_test, parallel_api_test, render_test
from pettingzoo.utils.conversions import parallel_to_aec

import uwb_env
from uwb_env.config import ConfigError
from uwb_env.env import CalibrationSchedulingEnv, rollout


def test_parallel_api():
    parallel_api_test(uwb_env.parallel_env(max_cycles=60), num_cycles=80)


def test_aec_api():
    api_test(parallel_to_aec(uwb_env.parallel_env(max_cycles=40)), num_cycles=50)


def test_max_cycles():
    class Module:  # max_cycles_test wants a module with parallel_env/env factories
        @staticmethod
        def parallel_env(max_cycles):
            return uwb_env.parallel_env(max_cycles=max_cycles)

        @staticmethod
        def env(max_cycles):
            return parallel_to_aec(uwb_env.parallel_env(max_cycles=max_cycles))

    max_cycles_test(Module)


def test_render_rgb_array():
    pytest.importorskip("matplotlib")
    render_test(lambda render_mode=None: parallel_to_aec(uwb_env.parallel_env(max_cycles=10, render_mode=render_mode)),
                custom_tests={"rgb_array": lambda frame: frame.ndim == 3 and frame.shape[2] == 3})


def test_scheduler_env_check_env_and_registration():
    check_env(CalibrationSchedulingEnv(max_cycles=30), skip_render_check=True)
    env = gymnasium.make("uwb_env/CalibrationScheduling-v0", max_cycles=20)
    obs, _ = env.reset(seed=3)
    assert obs.dtype == np.float32 and env.observation_space.contains(obs)
    steps, truncated = 0, False
    while not truncated:
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        assert not terminated and env.observation_space.contains(obs)
        steps += 1
    assert steps == 20


def _trace(env, seed, steps=120):
    obs, _ = env.reset(seed=seed)
    out = []
    for k in range(steps):
        actions = {a: int(k % 30 == 0) for a in env.agents}
        obs, rewards, _, _, infos = env.step(actions)
        out.append(np.concatenate([obs[a] for a in env.agents] + [[rewards["anchor_0"]]]))
    return np.array(out)


def test_multi_step_determinism_through_the_solver():
    a = _trace(uwb_env.parallel_env(), 11)
    b = _trace(uwb_env.parallel_env(), 11)
    c = _trace(uwb_env.parallel_env(), 12)
    for k in range(len(a)):
        np.testing.assert_array_equal(a[k], b[k], err_msg=f"step {k}")
    assert not np.array_equal(a, c)


def test_pickling_roundtrip():
    env = uwb_env.parallel_env(max_cycles=30)
    env.reset(seed=5)
    clone = pickle.loads(pickle.dumps(env))
    np.testing.assert_array_equal(_trace(env, 9, 20), _trace(clone, 9, 20))


def test_observations_are_float32_inside_their_spaces():
    env = uwb_env.parallel_env(max_cycles=300)
    obs, _ = env.reset(seed=0)
    while env.agents:
        for agent, o in obs.items():
            assert o.dtype == np.float32 and env.observation_space(agent).contains(o), (agent, o)
        obs, *_ = env.step({a: int(np.random.default_rng(0).random() < 0.05) for a in env.agents})


def test_invalid_actions_and_config_raise_clear_errors():
    env = uwb_env.parallel_env()
    env.reset(seed=0)
    with pytest.raises(ValueError, match="anchor_1"):
        env.step({"anchor_0": 0, "anchor_1": 7, "anchor_2": 0, "anchor_3": 0})
    with pytest.raises(KeyError, match="anchor_3"):
        env.step({"anchor_0": 0, "anchor_1": 0, "anchor_2": 0})
    with pytest.raises(ConfigError, match="max_cycle"):
        uwb_env.parallel_env(max_cycle=10)
    with pytest.raises(ValueError, match="render_mode"):
        uwb_env.parallel_env(render_mode="video")


def test_never_calibrating_lets_anchor_error_grow_and_a_calibration_reduces_it():
    env = uwb_env.parallel_env(max_cycles=500, sim={"odometry": {"model": "uniform", "uniform_error_m": 0.05}})
    env.reset(seed=1)
    errors = []
    for _ in range(300):
        _, _, _, _, infos = env.step({a: 0 for a in env.agents})
        errors.append(infos["anchor_0"]["mean_anchor_error_m"])
    assert np.mean(errors[-20:]) > 3 * np.mean(errors[:5])
    before = errors[-1]
    infos = None
    for k in range(20):
        _, _, _, _, infos = env.step({a: int(k == 0) for a in env.agents})
        if infos["anchor_0"]["round_finished"]:
            break
    assert infos["anchor_0"]["round_finished"]
    assert infos["anchor_0"]["mean_anchor_error_m"] < 0.5 * before


def test_round_takes_several_steps_tags_are_not_refixed_and_requests_are_ignored():
    env = uwb_env.parallel_env()
    env.reset(seed=2)
    env.step({a: 0 for a in env.agents})
    fix_before = env.system.tag_fix.copy()
    _, _, _, _, infos = env.step({a: 1 for a in env.agents})
    assert infos["anchor_0"]["round_started"] and infos["anchor_0"]["calibrating"]
    np.testing.assert_array_equal(env.system.tag_fix, fix_before)  # held, not re-fixed
    steps = 1
    while True:
        _, _, _, _, infos = env.step({a: 1 for a in env.agents})
        steps += 1
        assert infos["anchor_0"]["requests_ignored"] == 4
        if infos["anchor_0"]["round_finished"]:
            break
        np.testing.assert_array_equal(env.system.tag_fix, fix_before)
    assert steps == int(np.ceil(0.9 / 0.2))  # 0.9 s round at dt 0.2 s
    assert infos["anchor_0"]["calibration_count"] == 2  # the reset calibration + this one


@pytest.mark.parametrize("trigger, requests, starts", [("any", 1, True), ("majority", 2, False),
                                                       ("majority", 3, True), ("all", 3, False), ("all", 4, True)])
def test_trigger_rules(trigger, requests, starts):
    env = uwb_env.parallel_env(trigger=trigger)
    env.reset(seed=0)
    _, _, _, _, infos = env.step({a: int(i < requests) for i, a in enumerate(env.agents)})
    assert infos["anchor_0"]["round_started"] is starts


def test_calibrate_and_move_mode_drives_the_anchors():
    env = uwb_env.parallel_env(action_mode="calibrate_and_move", move_headings=4)
    env.reset(seed=0)
    assert env.action_space("anchor_0").n == 10
    start = env.system.world.anchors_true.copy()
    for _ in range(10):
        env.step({a: 4 for a in env.agents})  # request 0, "stop"
    np.testing.assert_allclose(env.system.world.anchors_true, start, atol=0.2)  # only jitter
    for _ in range(10):
        env.step({a: 0 for a in env.agents})  # heading -pi at move speed
    assert (env.system.world.anchors_true[:, 0] < start[:, 0] - 0.3).any()


def test_rollout_hook_with_a_user_policy():
    class EveryK:
        uses_ground_truth = False

        def __init__(self, k):
            self.k, self.t = k, 0

        def reset(self, seed=None):
            self.t = 0

        def act(self, observations, infos):
            self.t += 1
            return {a: int(self.t % self.k == 0) for a in observations}

    res = rollout(uwb_env.parallel_env(max_cycles=100), EveryK(20), seed=0)
    assert res.steps == 100 and res.round_started.sum() == 5
    s = res.summary()
    assert s["calibrations_per_min"] == pytest.approx(5 / (100 * 0.2 / 60))
    assert 0 < s["mean_tag_error_m"] < 2


def test_planar_metrics_equal_the_general_frame_formulas():
    """The 2D fast path (plain complex arithmetic) against the frame-by-frame numpy formulas."""
    from uwb_env.localization import rigid_align

    env = uwb_env.parallel_env(max_cycles=400)
    env.reset(seed=11)
    s = env.system
    for t in range(120):
        env.step({a: int(t % 40 == 0) for a in env.agents})
        if t % 20:
            continue
        fast = s._planar_errors()
        truth_a = s.world.to_estimate_frame(s.world.anchors_true)
        truth_t = s.world.to_estimate_frame(s.world.tags_true)
        rot, trans = rigid_align(truth_a, s.world.anchors_est, allow_reflection=False)
        frames = {"constellation": (truth_a @ rot.T + trans, truth_t @ rot.T + trans), "fixed": (truth_a, truth_t)}
        for frame, (ref_a, ref_t) in frames.items():
            np.testing.assert_allclose(fast["anchor", frame], np.linalg.norm(s.world.anchors_est - ref_a, axis=1),
                                       atol=1e-9)
            tag = np.linalg.norm(s.tag_fix - ref_t, axis=1)
            tag = np.where(np.isfinite(tag), np.minimum(tag, s.config.error_cap_m), s.config.error_cap_m)
            np.testing.assert_allclose(fast["tag", frame], tag, atol=1e-9)
        a, b = s.world.anchors_est[1] - s.world.anchors_est[0], truth_a[1] - truth_a[0]
        assert fast["rotation"] == pytest.approx(abs(np.arctan2(a[0] * b[1] - a[1] * b[0], a @ b)), abs=1e-12)


def test_three_dimensional_env_steps_with_finite_metrics():
    env = uwb_env.parallel_env(sim={"dim": 3, "n_anchors": 5}, max_cycles=60)
    obs, _ = env.reset(seed=0)
    for t in range(60):
        obs, rewards, _, _, infos = env.step({a: int(t % 20 == 0) for a in env.agents})
        for agent, o in obs.items():
            assert env.observation_space(agent).contains(o)
        info = infos["anchor_0"]
        assert np.isfinite([info["mean_tag_error_m"], info["mean_anchor_error_m"], info["rotation_error_rad"],
                            info["mean_tag_error_fixed_frame_m"], rewards["anchor_0"]]).all()
    assert info["calibration_count"] >= 3
