import json

import numpy as np
import pytest

pytest.importorskip("stable_baselines3", reason="the 'train' extra is not installed")

from uwb_env.agents.learned import LearnedPolicy  # noqa: E402
from uwb_env.agents.registry import make_policy  # noqa: E402
from uwb_env.training.train import Args, latest_checkpoint, load_hyperparams, main  # noqa: E402
from uwb_env.training.vec_env import ParallelEnvVecEnv  # noqa: E402
from uwb_env import parallel_env  # noqa: E402
from uwb_env.env.policy import rollout  # noqa: E402

TINY = ["n_envs=2", "n_steps=64", "batch_size=64", "n_epochs=1"]


def _args(out, **kw):
    base = dict(total_timesteps=256, out=str(out), hp=TINY, checkpoint_freq=128, eval_freq=128, eval_episodes=1,
                progress_bar=False, env_config=None)
    return Args(**(base | kw))


def test_short_run_writes_model_checkpoint_logs_and_resumes(tmp_path, short_episodes):
    out = tmp_path / "run"
    record = main(_args(out, env_config=short_episodes))
    assert record["num_timesteps"] == 256
    for name in ("model.zip", "vecnormalize.pkl", "run.json"):
        assert (out / name).is_file()
    assert latest_checkpoint(out / "checkpoints")[1] == 256
    assert any((out / "tb").rglob("events.out.tfevents*"))
    assert (out / "eval" / "evaluations.npz").is_file()
    # the best model (by the validation EvalCallback) is loadable like the final one
    assert (out / "best" / "vecnormalize.pkl").is_file() and (out / "best" / "run.json").is_file()
    assert LearnedPolicy.load(out / "best" / "best_model.zip").kind == "scheduler"
    saved = json.loads((out / "run.json").read_text())
    assert saved["hyperparams"]["n_steps"] == 64 and saved["env_config"]["max_cycles"] == 40

    # A second call with a larger budget continues from the checkpoint's step count.
    resumed = main(_args(out, env_config=short_episodes, total_timesteps=512))
    assert resumed["resumed_from_steps"] == 256
    assert resumed["num_timesteps"] == 512

    policy = make_policy(f"learned:{out / 'model.zip'}")
    assert isinstance(policy, LearnedPolicy) and policy.kind == "scheduler"
    result = rollout(parallel_env(max_cycles=30), policy, seed=3)
    assert result.steps == 30 and np.isfinite(result.tag_error_m).all()


def test_same_seed_same_model(tmp_path, short_episodes):
    a = main(_args(tmp_path / "a", env_config=short_episodes, eval_freq=0, seed=7))
    b = main(_args(tmp_path / "b", env_config=short_episodes, eval_freq=0, seed=7))
    assert a["num_timesteps"] == b["num_timesteps"]
    pa = LearnedPolicy.load(tmp_path / "a" / "model.zip").model.policy.state_dict()
    pb = LearnedPolicy.load(tmp_path / "b" / "model.zip").model.policy.state_dict()
    for key in pa:
        assert np.array_equal(pa[key].numpy(), pb[key].numpy()), key


def test_shared_policy_over_the_parallel_env(tmp_path, short_episodes):
    out = tmp_path / "par"
    main(_args(out, env="parallel", env_config=short_episodes, hp=["n_envs=1", "n_steps=32", "batch_size=64",
                                                                   "n_epochs=1"], eval_freq=0))
    policy = LearnedPolicy.load(out / "model.zip")
    assert policy.kind == "parallel"
    actions = policy.act(*parallel_env().reset(seed=0))
    assert set(actions) == {f"anchor_{i}" for i in range(4)} and set(actions.values()) <= {0, 1}


def test_vec_env_adapter_reports_truncation_and_resets():
    venv = ParallelEnvVecEnv([lambda: parallel_env(max_cycles=3) for _ in range(2)])
    assert venv.num_envs == 8
    venv.seed(11)
    obs = venv.reset()
    assert obs.shape == (8, venv.observation_space.shape[0]) and obs.dtype == np.float32
    for step in range(3):
        obs, rewards, dones, infos = venv.step(np.ones(8, dtype=np.int64))
    assert dones.all()
    assert all(info["TimeLimit.truncated"] for info in infos)
    assert all(venv.observation_space.contains(info["terminal_observation"]) for info in infos)
    assert venv.get_attr("num_steps") == [0] * 8  # the copies were reset automatically
    # seeding makes resets reproducible
    venv.seed(11)
    again = venv.reset()
    venv.seed(11)
    np.testing.assert_array_equal(again, venv.reset())


def test_bad_arguments_are_named(tmp_path):
    with pytest.raises(ValueError, match="algo='sac'"):
        main(Args(algo="sac", out=str(tmp_path)))
    with pytest.raises(ValueError, match="hp='lr'"):
        load_hyperparams(Args(hp=["lr"]))
    with pytest.raises(FileNotFoundError, match="nope.zip"):
        LearnedPolicy.load(tmp_path / "nope.zip")


def test_batched_training_mode(tmp_path, short_episodes):
    out = tmp_path / "batched"
    record = main(_args(out, env="batched", env_config=short_episodes, eval_freq=0,
                        hp=["n_envs=8", "n_steps=32", "batch_size=64", "n_epochs=1"]))
    assert record["num_timesteps"] == 256
    policy = LearnedPolicy.load(out / "model.zip")
    assert policy.kind == "scheduler"  # same observations as the single scheduler env
    assert rollout(parallel_env(max_cycles=10), policy, seed=0).steps == 10


def test_shipped_model_runs_through_the_hook():
    from uwb_env.agents.registry import shipped_model
    from uwb_env.training.evaluate import default_policies

    assert shipped_model("ppo_scheduler").is_file()
    assert "learned:ppo_scheduler" in default_policies()
    policy = make_policy("learned:ppo_scheduler")
    # trained on free motion (the old default, now training/scenarios/free_motion.yml)
    free = {"anchor_motion": {"model": "heading"}, "tag_motion": {"model": "heading"}}
    result = rollout(parallel_env(max_cycles=300, sim=free), policy, seed=1)
    assert result.steps == 300 and 0 < result.round_started.sum() < 100  # it calibrates, not always


def test_learned_policy_refuses_a_team_of_another_size():
    policy = make_policy("learned:ppo_scheduler")  # trained with 4 anchors
    env = parallel_env(sim={"n_anchors": 5})
    with pytest.raises(ValueError, match="another number of anchors"):
        policy.act(*env.reset(seed=0))


def test_hp_overrides_keep_numbers_numbers():
    hp = load_hyperparams(Args(hp=["learning_rate=1e-4", "policy_kwargs={net_arch: [32]}", "normalize=false"]))
    assert hp["learning_rate"] == 1e-4 and isinstance(hp["learning_rate"], float)
    assert hp["policy_kwargs"] == {"net_arch": [32]} and hp["normalize"] is False
