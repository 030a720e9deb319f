"""Conformance with RL clients nobody here wrote: PettingZoo's and Gymnasium's own checks, SB3's."""

import gymnasium
import numpy as np
import pytest
from pettingzoo.test import api_test, max_cycles_test, parallel_api_test, parallel_seed_test, render_test, seed_test

import uwb_env
from uwb_env import uwb_calibration_v0


def test_pettingzoo_api_tests():
    parallel_api_test(uwb_calibration_v0.parallel_env(max_cycles=30), num_cycles=40)
    api_test(uwb_calibration_v0.env(max_cycles=30), num_cycles=40)


def test_pettingzoo_seed_and_max_cycles_tests():
    parallel_seed_test(lambda: uwb_calibration_v0.parallel_env(max_cycles=20), num_cycles=20)
    seed_test(lambda: uwb_calibration_v0.env(max_cycles=20), num_cycles=20)
    max_cycles_test(uwb_calibration_v0)


def test_pettingzoo_render_test():
    render_test(lambda render_mode=None: uwb_calibration_v0.env(max_cycles=10, render_mode=render_mode))


def test_infos_have_one_schema_at_reset_and_every_step():
    env = uwb_env.parallel_env(max_cycles=30)
    _, infos = env.reset(seed=0)
    schema = {k: (type(v), np.shape(v)) for k, v in infos["anchor_0"].items()}
    assert len([k for k in schema if k.startswith("reward_")]) == 4
    # only numbers, flags and fixed-shape arrays: TorchRL turns each value into a tensor
    assert all(t in (int, float, bool, np.ndarray) for t, _ in schema.values()), schema
    for t in range(30):
        _, _, _, _, infos = env.step({a: int(t % 7 == 0) for a in env.agents})
        for info in infos.values():
            assert {k: (type(v), np.shape(v)) for k, v in info.items()} == schema
    assert isinstance(env.calibration_error, str)


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


# -- heavier clients: the `clients` extra (pip install -e ".[clients]"), run in CI's third stage --

def test_torchrl_pettingzoo_wrapper_specs_and_collector():
    pytest.importorskip("torchrl")
    from torchrl.collectors import Collector
    from torchrl.envs.libs.pettingzoo import PettingZooWrapper
    from torchrl.envs.utils import check_env_specs

    env = PettingZooWrapper(uwb_calibration_v0.parallel_env(max_cycles=10), categorical_actions=True, seed=0)
    check_env_specs(env)
    assert env.group_map == {"anchor": [f"anchor_{i}" for i in range(4)]}
    collector = Collector(env, None, frames_per_batch=20, total_frames=40)
    batches = list(collector)
    collector.shutdown()
    assert len(batches) == 2
    info = batches[0]["next", "anchor", "info"]
    assert info["mean_tag_error_m"].shape == (20, 4) and bool((info["mean_tag_error_m"] >= 0).all())
    assert int(batches[0]["next", "done"].sum()) == 2  # two episodes of 10 steps in 20 frames


def test_torchrl_gym_env_by_id():
    pytest.importorskip("torchrl")
    from torchrl.envs.libs.gym import GymEnv
    from torchrl.envs.utils import check_env_specs

    env = GymEnv("uwb_env/CalibrationScheduling-v0", max_cycles=10)  # passes frameskip=1: a TypeError
    check_env_specs(env)
    rollout = env.rollout(12)
    assert rollout["next", "observation"].shape == (10, 40) and bool(rollout["next", "truncated"][-1])


def test_tianshou_collector():
    pytest.importorskip("tianshou")
    from tianshou.algorithm.algorithm_base import Policy
    from tianshou.data import Batch, Collector, VectorReplayBuffer
    from tianshou.env import DummyVectorEnv

    class CalibrateEveryStep(Policy):  # Tianshou's RandomActionPolicy draws floats for Discrete
        def forward(self, batch, state=None, **kwargs):
            return Batch(act=np.ones(len(batch.obs), dtype=np.int64), state=state)

    def make():
        return gymnasium.make("uwb_env/CalibrationScheduling-v0", max_cycles=10)

    venv = DummyVectorEnv([make, make])
    collector = Collector(CalibrateEveryStep(action_space=venv.action_space[0]), venv, VectorReplayBuffer(100, 2))
    collector.reset(reset_buffer=True, gym_reset_kwargs={"seed": 0})
    stats = collector.collect(n_episode=2)
    assert stats.n_collected_episodes == 2 and stats.n_collected_steps == 20
    assert np.all(np.isfinite(stats.returns)) and np.all(stats.returns < 0)
