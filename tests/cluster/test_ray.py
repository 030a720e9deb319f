"""Ray RLlib / Tune: run in CI's second virtual environment (the ``cluster`` extra).

In an environment without Ray these tests skip; ``.ci/run`` runs them where Ray is installed.
"""

import json

import numpy as np
import pytest

ray = pytest.importorskip("ray", reason="the 'cluster' extra is not installed")

from uwb_env.agents.registry import make_policy  # noqa: E402

import uwb_env  # noqa: E402
from uwb_env.env.policy import rollout  # noqa: E402

TINY = ["train_batch_size_per_learner=200", "minibatch_size=100", "num_epochs=1"]


@pytest.fixture(scope="module", autouse=True)
def local_ray():
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()


def test_one_rllib_iteration_checkpoints_restores_and_acts(tmp_path, short_episodes):
    from uwb_env.training.train_rllib import Args, main

    out = tmp_path / "rllib"
    record = main(Args(iterations=1, out=str(out), env_config=short_episodes, hp=TINY, num_env_runners=0))
    assert record["iterations_done"] == 1 and record["num_timesteps"] >= 200
    assert (out / "checkpoint" / "rllib_checkpoint.json").exists()
    saved = json.loads((out / "run.json").read_text())
    assert saved["algo"] == "rllib_ppo" and {"num_timesteps", "training_wall_s", "env_steps_per_s"} <= set(saved)

    # resuming continues from the checkpoint instead of starting over
    again = main(Args(iterations=2, out=str(out), env_config=short_episodes, hp=TINY, num_env_runners=0))
    assert again["resumed_from_iterations"] == 1 and again["iterations_done"] == 2
    assert again["num_timesteps"] > record["num_timesteps"]

    policy = make_policy(f"rllib:{out / 'checkpoint'}")
    result = rollout(uwb_env.parallel_env(max_cycles=20), policy, seed=5)
    assert result.steps == 20 and np.isfinite(result.tag_error_m).all()


def test_one_policy_per_anchor(tmp_path, short_episodes):
    from uwb_env.training.train_rllib import Args, main

    out = tmp_path / "per"
    main(Args(iterations=1, out=str(out), env_config=short_episodes, hp=TINY, num_env_runners=0, policy="per_anchor"))
    policy = make_policy(f"rllib:{out / 'checkpoint'}")
    assert sorted(policy.modules) == [f"anchor_{i}" for i in range(4)]
    actions = policy.act(*uwb_env.parallel_env().reset(seed=0))
    assert set(actions.values()) <= {0, 1}


def test_two_trial_tune_sweep_writes_the_harness_files(tmp_path):
    from uwb_env.training.sweep_tune import Args, main

    out = tmp_path / "sweep"
    record = main(Args(kind="harness", policies=["fixed:10", "threshold:0.15"], seeds=2, max_cycles=30, out=str(out)))
    assert record["trials"] == 2
    for name in ("episodes.csv", "summary.csv", "summary.json", "tradeoff.png"):
        assert (out / name).exists()
    summary = json.loads((out / "summary.json").read_text())["summary"]
    assert {r["policy"] for r in summary} == {"fixed:10", "threshold:0.15"}
    assert all(r["episodes"] == 2 for r in summary)


def test_cli_train_backend_rllib(tmp_path, short_episodes, capsys):
    from uwb_env.cli import main

    out = tmp_path / "cli"
    assert main(["train", "--backend", "rllib", "--iterations", "1", "--num-env-runners", "0", "--out", str(out),
                 "--env-config", short_episodes, "--hp", *TINY]) == 0
    assert (out / "checkpoint" / "rllib_checkpoint.json").exists()
    assert "rllib:" in capsys.readouterr().out


def test_sb3_hyperparameter_sweep_on_tune(tmp_path, short_episodes):
    from uwb_env.training.sweep_tune import Args, main

    out = tmp_path / "sb3"
    record = main(Args(kind="sb3", grid=["learning_rate=1e-4,3e-4"], total_timesteps=256, config=short_episodes,
                       out=str(out)))
    assert [t["hp"]["learning_rate"] for t in sorted(record["trials"], key=lambda t: t["hp"]["learning_rate"])] \
        == [1e-4, 3e-4]
    assert all((tmp_path / "sb3" / "trials" / f"learning_rate={lr}" / "model.zip").exists() for lr in (1e-4, 3e-4))
    assert json.loads((out / "sb3_sweep.json").read_text())["kind"] == "sb3"
