import numpy as np
import pytest
from uwb_env.agents.baselines import FixedIntervalPolicy

from uwb_env import parallel_env
from uwb_env.batch import BatchedSystem
from uwb_env.config import EnvConfig
from uwb_env.env.policy import rollout
from uwb_env.env.vector_env import CalibrationSchedulingVectorEnv


def test_batched_statistics_match_the_single_env():
    cfg = EnvConfig.from_dict({"max_cycles": 200})
    venv = CalibrationSchedulingVectorEnv(24, config=cfg)
    venv.reset(seed=0)
    tag, anchor, busy = [], [], []
    for t in range(200):
        _, _, _, _, info = venv.step(np.full(24, int((t + 1) % 10 == 0)))
        tag.append(info["mean_tag_error_m"])
        anchor.append(info["mean_anchor_error_m"])
        busy.append(info["calibrating_fraction"])
    single = [rollout(parallel_env(config=cfg), FixedIntervalPolicy(10), seed=s) for s in range(12)]
    s_tag = np.mean([r.tag_error_m.mean() for r in single])
    s_anchor = np.mean([r.anchor_error_m.mean() for r in single])
    assert np.mean(busy) == pytest.approx(np.mean([r.calibrating.mean() for r in single]), abs=1e-9)
    assert np.mean(anchor) == pytest.approx(s_anchor, rel=0.2)
    assert np.median(np.concatenate(tag)) == pytest.approx(np.median([np.median(r.tag_error_m) for r in single]),
                                                          rel=0.25)
    assert 0.5 < np.mean(tag) / s_tag < 2.0
    # never calibrating: the anchors drift far more than with calibrations
    venv.reset(seed=1)
    for _ in range(100):
        _, _, _, _, info = venv.step(np.zeros(24, dtype=int))
    assert info["mean_anchor_error_m"].mean() > 2 * np.mean(anchor)


def test_vector_env_spaces_autoreset_and_seeding():
    venv = CalibrationSchedulingVectorEnv(4, max_cycles=6, autoreset_mode="SameStep")
    obs, _ = venv.reset(seed=3)
    assert obs.dtype == np.float32 and venv.observation_space.contains(obs)
    for t in range(6):
        obs, reward, term, trunc, info = venv.step(np.array([0, 1, 0, 1]))
        assert venv.observation_space.contains(obs) and reward.shape == (4,) and not term.any()
    assert trunc.all() and "final_obs" in info and venv.observation_space.contains(info["final_obs"])
    assert info["round_started"].dtype == bool
    a = CalibrationSchedulingVectorEnv(3, max_cycles=20)
    b = CalibrationSchedulingVectorEnv(3, max_cycles=20)
    oa, _ = a.reset(seed=9)
    ob, _ = b.reset(seed=9)
    for t in range(15):
        act = np.array([t % 7 == 0, 0, 1])
        oa, ra, *_ = a.step(act)
        ob, rb, *_ = b.step(act)
    np.testing.assert_array_equal(oa, ob)
    np.testing.assert_array_equal(ra, rb)
    with pytest.raises(ValueError, match="expected 3 values"):
        a.step(np.array([0, 2, 1]))


def test_batched_mode_rejects_3d():
    with pytest.raises(ValueError, match="2D only"):
        BatchedSystem(EnvConfig.from_dict({"sim": {"dim": 3}}), 2)


def test_sb3_adapter_reports_truncation():
    pytest.importorskip("stable_baselines3")
    from uwb_env.training.vec_env import BatchedSchedulerVecEnv

    venv = BatchedSchedulerVecEnv(5, {"max_cycles": 4})
    venv.seed(0)
    obs = venv.reset()
    assert obs.shape == (5, venv.observation_space.shape[0])
    for _ in range(4):
        obs, rewards, dones, infos = venv.step(np.zeros(5, dtype=int))
    assert dones.all() and all(i["TimeLimit.truncated"] for i in infos)
    assert all(venv.observation_space.contains(i["terminal_observation"]) for i in infos)


def test_next_step_autoreset_is_the_default_and_gymnasium_wrappers_work():
    import gymnasium
    from gymnasium.vector import AutoresetMode
    from gymnasium.wrappers.vector import RecordEpisodeStatistics, TransformObservation

    import uwb_env  # noqa: F401  (registration)

    venv = gymnasium.make_vec("uwb_env/CalibrationScheduling-v0", num_envs=3, vectorization_mode="vector_entry_point",
                              max_cycles=5)
    assert isinstance(venv.unwrapped, CalibrationSchedulingVectorEnv)
    assert venv.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
    venv = TransformObservation(RecordEpisodeStatistics(venv), lambda o: o * 2.0, venv.observation_space)
    obs, _ = venv.reset(seed=[1, 2, 3])
    for _ in range(5):
        last, reward, term, trunc, info = venv.step(np.ones(3, dtype=int))
    assert trunc.all() and "episode" in info and np.allclose(info["episode"]["l"], 5)
    first, reward, term, trunc, info = venv.step(np.ones(3, dtype=int))  # the reset step
    assert not trunc.any() and (reward == 0).all() and not np.array_equal(first, last)
    with pytest.raises(ValueError, match="seed"):
        venv.reset(seed=[1, 2])


def test_batched_and_single_env_episode_statistics_agree_in_distribution():
    """48 batched copies against 48 single-env episodes (fixed:10, 150 steps): the per-episode
    mean tag and anchor errors come from the same distribution (two-sample KS), the busy
    fraction is identical. Catches a second copy of the dynamics drifting from the first."""
    from scipy.stats import ks_2samp

    cfg = EnvConfig.from_dict({"max_cycles": 150})
    venv = CalibrationSchedulingVectorEnv(48, config=cfg)
    venv.reset(seed=11)
    tag, anchor = np.zeros(48), np.zeros(48)
    for t in range(150):
        _, _, _, _, info = venv.step(np.full(48, int((t + 1) % 10 == 0)))
        tag += info["mean_tag_error_m"] / 150
        anchor += info["mean_anchor_error_m"] / 150
    single = [rollout(parallel_env(config=cfg), FixedIntervalPolicy(10), seed=100 + s) for s in range(48)]
    s_tag = np.array([r.tag_error_m.mean() for r in single])
    s_anchor = np.array([r.anchor_error_m.mean() for r in single])
    assert ks_2samp(tag, s_tag).pvalue > 0.01, (np.median(tag), np.median(s_tag))
    assert ks_2samp(anchor, s_anchor).pvalue > 0.01, (np.median(anchor), np.median(s_anchor))


def test_batched_reset_survives_first_calibrations_that_fail():
    """With almost every range lost the first round of most copies has no shape: reset does not
    raise, those copies keep their starting estimates and report no calibration."""
    cfg = EnvConfig.from_dict({"sim": {"ranging": {"dropout_probability": 0.97}}})
    system = BatchedSystem(cfg, 32)
    system.reset(np.random.default_rng(0))
    assert (system.calibration_count == 0).sum() > 16
    for t in range(12):
        system.step(np.full(32, t % 10 == 0))
    assert np.isfinite(system.errors_m()[0]).all()
