"""Conformance with RL clients nobody here wrote: PettingZoo's and Gymnasium's own checks, SB3's."""

import gymnasium
import numpy as np
import pytest
from pettingzoo.test import api_test, max_cycles_test, parallel_api_test, parallel_seed_test, render_test

import uwb_env
from uwb_env import uwb_calibration_v0


def test_pettingzoo_api_tests():
    parallel_api_test(uwb_calibration_v0.parallel_env(max_cycles=30), num_cycles=40)
    api_test(uwb_calibration_v0.env(max_cycles=30), num_cycles=40)


def test_pettingzoo_seed_and_max_cycles_tests():
    parallel_seed_test(lambda: uwb_calibration_v0.parallel_env(max_cycles=20), num_cycles=20)
    max_cycles_test(uwb_calibration_v0)


def test_pettingzoo_render_test():
    render_test(lambda render_mode=None: uwb_calibration_v0.env(max_cycles=10, render_mode=render_mode))


def test_infos_have_one_schema_at_reset_and_every_step():
    env = uwb_env.parallel_env(max_cycles=30)
    _, infos = env.reset(seed=0)
    schema = {k: type(v) for k, v in infos["anchor_0"].items()}
    terms = set(infos["anchor_0"]["reward_terms"])
    assert len(terms) == 4 and None not in schema.values() and type(None) not in schema.values()
    for t in range(30):
        _, _, _, _, infos = env.step({a: int(t % 7 == 0) for a in env.agents})
        for info in infos.values():
            assert {k: type(v) for k, v in info.items()} == schema
            assert set(info["reward_terms"]) == terms


def test_unknown_keyword_is_a_type_error_for_gym_clients():
    with pytest.raises(TypeError, match="frameskip"):
        gymnasium.make("uwb_env/CalibrationScheduling-v0", frameskip=1)
    with pytest.raises(TypeError):
        uwb_env.parallel_env(frameskip=1)


def test_gymnasium_and_sb3_env_checkers():
    from gymnasium.utils.env_checker import check_env

    env = gymnasium.make("uwb_env/CalibrationScheduling-v0", max_cycles=20)
    check_env(env.unwrapped)
    sb3 = pytest.importorskip("stable_baselines3.common.env_checker")
    sb3.check_env(gymnasium.make("uwb_env/CalibrationScheduling-v0", max_cycles=20).unwrapped)


@pytest.mark.parametrize("mode", ["sync", "async"])
def test_gymnasium_make_vec(mode):
    venv = gymnasium.make_vec("uwb_env/CalibrationScheduling-v0", num_envs=2, vectorization_mode=mode, max_cycles=5)
    obs, infos = venv.reset(seed=0)
    assert obs.shape[0] == 2 and obs.dtype == np.float32
    for _ in range(6):
        obs, rew, term, trunc, infos = venv.step(venv.action_space.sample())
    venv.close()
