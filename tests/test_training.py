import json

import numpy as np
import pytest

pytest.importorskip("stable_baselines3", reason="the 'train' extra is not installed")

from uwb_env.agents.learned import LearnedPolicy  # noqa: E402
from uwb_env.agents.registry import make_policy  # noqa: E402
from uwb_env.training.train import Args, latest_checkpoint, load_hyperparams, main  # noqa: E402
from uwb_env.training.evaluate import DEFAULT_TUNED  # noqa: E402
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
    # the main job's learned entry: the residual scheduler on the base rule that tuned best (the
    # highest validation return of the per-anchor rules and the team threshold), at its threshold
    from uwb_env.agents.per_anchor import BASE_FAMILIES, learned_base

    record = json.loads(DEFAULT_TUNED.read_text())
    family = max(BASE_FAMILIES, key=lambda f: record["families"][f]["best_return"])
    assert f"learned:anchor_set@{learned_base(record['tuned'][family])}" in default_policies()
    policy = make_policy("learned:ppo_scheduler")  # the earlier 4-anchor model stays loadable
    # trained on free motion (the old default, now training/scenarios/free_motion.yml)
    free = {"anchor_motion": {"model": "heading"}, "tag_motion": {"model": "heading"}}
    result = rollout(parallel_env(max_cycles=300, sim=free), policy, seed=1)
    assert result.steps == 300 and 0 < result.round_started.sum() < 100  # it calibrates, not always


@pytest.mark.parametrize("n_anchors", [3, 4, 5, 8, 16])
def test_shipped_anchor_set_model_runs_on_every_team_size(n_anchors):
    from uwb_env.agents.anchor_set import AnchorSetPolicy

    policy = make_policy("learned:anchor_set")
    assert isinstance(policy, AnchorSetPolicy) and policy.action_mode == "per_anchor"
    env = parallel_env(max_cycles=150, action_mode="per_anchor", sim={"n_anchors": n_anchors, "n_tags": 3})
    result = rollout(env, policy, seed=2)
    assert result.steps == 150 and np.isfinite(result.tag_error_m).all()


def test_learned_spec_base_threshold():
    policy = make_policy("learned:anchor_set@0.42")
    assert policy.base_threshold_m == 0.42
    assert make_policy("learned:anchor_set").base_threshold_m == 0.3  # the model's default base
    from uwb_env.agents.registry import PolicySpecError

    for bad, match in (("learned:anchor_set@", "needs a base threshold"), ("learned:anchor_set@-1", "base_threshold_m"),
                       ("learned:anchor_set@nan", "base_threshold_m"),
                       ("learned:anchor_set@abc", "must be a number in metres, got 'abc'"),
                       ("learned:ppo_scheduler@0.3", "only the per-anchor scheduler")):
        with pytest.raises(PolicySpecError, match=match):
            make_policy(bad)


def test_learned_spec_keeps_an_at_sign_inside_the_model_path(tmp_path):
    """A model under a directory named with '@' is a path, not a '@<base threshold>' spec."""
    from uwb_env.agents.registry import PolicySpecError

    shipped = make_policy("learned:ppo_scheduler")
    model = tmp_path / "run@night" / "model.zip"
    model.parent.mkdir()
    shipped.model.save(model)
    loaded = make_policy(f"learned:{model}")
    assert type(loaded) is type(shipped)
    with pytest.raises(PolicySpecError, match="only the per-anchor scheduler"):
        make_policy(f"learned:{model}@0.3")


def test_learned_policy_refuses_a_team_of_another_size():
    policy = make_policy("learned:ppo_scheduler")  # trained with 4 anchors
    env = parallel_env(sim={"n_anchors": 5})
    with pytest.raises(ValueError, match="another number of anchors"):
        policy.act(*env.reset(seed=0))


def test_hp_overrides_keep_numbers_numbers():
    hp = load_hyperparams(Args(hp=["learning_rate=1e-4", "policy_kwargs={net_arch: [32]}", "normalize=false"]))
    assert hp["learning_rate"] == 1e-4 and isinstance(hp["learning_rate"], float)
    assert hp["policy_kwargs"] == {"net_arch": [32]} and hp["normalize"] is False


# -- main job output and plots (uwb_env/progress.py, training/plots.py) ------------------------

def test_progress_writes_one_line_per_update_with_eta_in_a_log():
    import io

    from uwb_env.progress import progress

    log = io.StringIO()  # not a TTY: no carriage returns running together
    assert list(progress(range(5), 5, "job", stream=log, log_every_s=0.0)) == list(range(5))
    lines = log.getvalue().splitlines()
    assert "\r" not in log.getvalue() and lines[0].startswith("job  0/5") and "ETA ?" in lines[0]
    assert lines[-1].startswith("job  5/5 (100%)") and "ETA 0:00" in lines[-1] and len(lines) == 6


def test_plot_labels_carry_no_absolute_paths():
    from uwb_env.training.plots import short_label

    assert short_label("learned:/home/someone/runs/ppo/model.zip") == "learned:ppo"
    assert short_label("rllib:/abs/runs/rllib/checkpoint") == "rllib:rllib"
    assert short_label("fixed:10") == "fixed:10" and short_label("learned:ppo_scheduler") == "learned:ppo_scheduler"


def _fake_results(n_steps=50, seeds=3):
    rng = np.random.default_rng(0)
    specs = ["fixed:10", "never", "always", "oracle:0.3", "learned:/abs/path/run/model.zip"]
    sweep = [f"fixed:{k}" for k in (5, 20, 40)] + [f"threshold:{t}" for t in (0.1, 0.2)]
    episodes, summary = [], []
    for spec in specs + sweep:
        scale = 3.0 if spec in ("always", "fixed:5") else 0.15
        for s in range(seeds):
            episodes.append({"policy": spec, "seed": s, "uses_ground_truth": spec.startswith("oracle"),
                             "tag_error_trace": scale * rng.lognormal(0, 0.3, n_steps)})
        group = "main" if spec in specs else "sweep_" + spec.partition(":")[0]
        summary.append({"policy": spec, "group": group, "uses_ground_truth": spec.startswith("oracle"),
                        "mean_tag_error_m": scale * (1 + 0.1 * len(spec) / 10),
                        "calibrations_per_min": 0.0 if spec == "never" else 60.0 / (1 + len(spec))})
    return {"summary": summary, "episodes": episodes, "dt_s": 0.2}


def test_evaluation_plots_are_written(tmp_path):
    pytest.importorskip("matplotlib")
    from uwb_env.training.plots import evaluation_plots

    paths = evaluation_plots(_fake_results(), str(tmp_path))
    assert sorted(p.rsplit("/", 1)[1] for p in paths) == ["boxplot.png", "error_over_time.png", "tradeoff.png"]
    assert all((tmp_path / p.rsplit("/", 1)[1]).stat().st_size > 10_000 for p in paths)


def test_plots_skip_without_matplotlib(tmp_path, monkeypatch, capsys):
    import sys

    from uwb_env.training import plots

    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import fails as in a core-only install
    assert plots.evaluation_plots(_fake_results(), str(tmp_path)) == []
    assert plots.paper_figures({}, [], [], [], {}, str(tmp_path), "") == []
    assert "skipping plots" in capsys.readouterr().err and not list(tmp_path.iterdir())


def test_summary_csv_floats_rounded_and_gt_note_only_with_a_gt_policy(tmp_path):
    import csv

    from uwb_env.training.evaluate import Args, evaluate, format_table

    results = evaluate(Args(policies=["fixed:10", "never"], seeds=2, max_cycles=20, sweep=False, workers=1,
                            out=str(tmp_path), plots=False, progress=False))
    assert "(GT)" not in format_table(results["summary"])
    with open(tmp_path / "summary.csv") as f:
        values = [v for row in csv.DictReader(f) for v in row.values()]
    def as_float(v):
        try:
            return float(v)
        except ValueError:
            return None

    numbers = [(v, as_float(v)) for v in values if as_float(v) is not None and "." in v]
    assert numbers and all(float(f"{x:.6g}") == x and len(v) < 14 for v, x in numbers)  # not 5.8999999999999995
    assert results["written"] and not any(p.endswith(".png") for p in results["written"])


def test_default_training_path_is_batched_where_the_config_allows():
    from uwb_env.training.train import resolve_env

    assert resolve_env(Args(), {"sim": {"dim": 2}}) == "batched"
    assert resolve_env(Args(), {"sim": {"dim": 3}}) == "scheduler"  # the batched core is 2D
    assert resolve_env(Args(), {"action_mode": "per_anchor"}) == "scheduler"
    assert resolve_env(Args(vec_env="dummy"), {}) == "scheduler"  # asked for one Gymnasium env per copy
    assert resolve_env(Args(env="parallel"), {}) == "parallel"
