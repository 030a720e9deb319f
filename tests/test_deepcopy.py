"""copy.deepcopy / pickle of an env mid-episode continue bit-identically (and independently)."""

import copy
import pickle

import numpy as np
import pytest

from uwb_env.env.parallel_env import UWBCalibrationParallelEnv
from uwb_env.env.scheduler_env import CalibrationSchedulingEnv


def _same(a, b) -> bool:
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, (np.ndarray, list, tuple)):
        return np.array_equal(np.asarray(a), np.asarray(b), equal_nan=True)
    return a == b or (a != a and b != b)  # NaN == NaN here


def _actions(t: int, agents) -> dict:
    return {a: int(t % 9 == 0) for a in agents}


@pytest.mark.parametrize("clone", [copy.deepcopy, lambda e: pickle.loads(pickle.dumps(e))], ids=["deepcopy", "pickle"])
@pytest.mark.parametrize("split_step", [25, 28])  # 28: in the middle of a calibration round
def test_parallel_env_clone_continues_identically(clone, split_step):
    env = UWBCalibrationParallelEnv(max_cycles=80)
    env.reset(seed=11)
    for t in range(split_step):
        env.step(_actions(t, env.agents))
    if split_step == 28:
        assert env.system.world.round is not None
    twin = clone(env)
    assert twin.agents == env.agents and twin.num_steps == env.num_steps
    for t in range(split_step, 80):
        out, out_twin = env.step(_actions(t, env.agents)), twin.step(_actions(t, twin.agents))
        for part, part_twin in zip(out, out_twin, strict=True):
            assert _same(part, part_twin), t
    assert env.agents == twin.agents == []


def test_clone_is_independent_of_the_original():
    env = UWBCalibrationParallelEnv(max_cycles=60)
    env.reset(seed=2)
    twin = copy.deepcopy(env)
    state = env.np_random.bit_generator.state
    for t in range(20):
        twin.step(_actions(t, twin.agents))
    assert env.np_random.bit_generator.state == state  # stepping the copy left the original's generator
    assert env.num_steps == 0


def test_scheduler_env_clone_continues_identically():
    env = CalibrationSchedulingEnv(max_cycles=70)
    env.reset(seed=5)
    for t in range(12):
        env.step(int(t % 6 == 0))
    twin = copy.deepcopy(env)
    # One generator shared by the wrapper and the parallel env survives the copy.
    assert twin.parallel.np_random is twin.np_random is twin.parallel.system.world.rng
    for t in range(12, 70):
        out, out_twin = env.step(int(t % 6 == 0)), twin.step(int(t % 6 == 0))
        for part, part_twin in zip(out, out_twin, strict=True):
            assert _same(part, part_twin), t


def test_batched_vector_env_clone_continues_identically():

    from uwb_env.env.vector_env import CalibrationSchedulingVectorEnv

    env = CalibrationSchedulingVectorEnv(num_envs=4, max_cycles=60)
    env.reset(seed=[1, 2, 3, 4])
    for t in range(30):
        env.step(np.array([t % 10 == 0] * 4))
    clones = [copy.deepcopy(env), pickle.loads(pickle.dumps(env))]
    # past the time limit: the autoreset happens in the clones too
    actions = [np.array([t % 7 == 0, t % 5 == 0, False, True]) for t in range(40)]
    ref = [env.step(a) for a in actions]
    for clone in clones:
        out = [clone.step(a) for a in actions]
        for (o1, r1, te1, tr1, _), (o2, r2, te2, tr2, _) in zip(ref, out, strict=True):
            np.testing.assert_array_equal(o1, o2)
            np.testing.assert_array_equal(r1, r2)
            np.testing.assert_array_equal(te1 | tr1, te2 | tr2)
