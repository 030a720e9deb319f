"""The scheduler distilled from the rollout reference: the rule unless a predicted gain pays."""

import json

import numpy as np
import pytest
from uwb_env.agents.distilled import (
    MOVES,
    TEAM_FEATURES,
    DistilledPolicy,
    GainModel,
    base_spec,
    parse_base,
    team_features,
)
from uwb_env.agents.per_anchor import TEAM_ROUND
from uwb_env.agents.registry import make_policy
from uwb_env.training import train_distilled

from uwb_env.config import EnvConfig
from uwb_env.env.parallel_env import UWBCalibrationParallelEnv
from uwb_env.system import OBS_FIELDS

F = len(TEAM_FEATURES)


def constant_model(team: float, wait: float, decide: int = 10) -> GainModel:
    """Predicts the same gains everywhere (a zero weight layer and the gains as its bias)."""
    return GainModel(np.zeros(F), np.ones(F), ((np.zeros((F, 2)), np.array([team, wait])),), 60, decide)


def run(policy, seed=3, max_cycles=80, **sim):
    config = EnvConfig.from_dict({"action_mode": "per_anchor", "max_cycles": max_cycles, "sim": sim})
    env = UWBCalibrationParallelEnv(config)
    policy.configure(config) if hasattr(policy, "configure") else None
    policy.reset(seed)
    obs, infos = env.reset(seed=seed)
    actions, returns = [], 0.0
    while env.agents:
        act = policy.act(obs, infos)
        actions.append(act)
        obs, rewards, _, _, infos = env.step(act)
        returns += next(iter(rewards.values()))
    return actions, returns


def test_base_specs_parse_like_the_learned_residuals():
    assert parse_base("drift:0.21") == ("drift", 0.21)
    assert parse_base("0.3") == ("total", 0.3)
    assert parse_base("team:1") == ("team", 1.0)
    assert base_spec("drift:0.2121") == "per_anchor_drift:0.2121"
    assert base_spec("0.3") == "per_anchor_threshold:0.3"
    assert base_spec("team:1") == "threshold:1"


def test_team_features_do_not_depend_on_anchor_order_or_team_size():
    rng = np.random.default_rng(0)
    own = rng.uniform(0.01, 1.0, (5, len(OBS_FIELDS)))
    base = np.array([0, 1, 0, 2, 1])
    f = team_features(own, base, 0.2, 0.2, 100, 60)
    perm = rng.permutation(5)
    np.testing.assert_allclose(team_features(own[perm], base[perm], 0.2, 0.2, 100, 60), f)
    assert f.shape == team_features(own[:3], base[:3], 0.2, 0.2, 100, 60).shape == (F,)
    assert f[TEAM_FEATURES.index("horizon_left")] == 1.0
    assert team_features(own, base, 0.2, 0.2, 30, 60)[TEAM_FEATURES.index("horizon_left")] == 0.5


def test_gain_model_round_trips_and_refuses_other_files(tmp_path):
    rng = np.random.default_rng(1)
    model = GainModel(rng.normal(size=F), rng.uniform(0.5, 2, F),
                      ((rng.normal(size=(F, 8)), rng.normal(size=8)), (rng.normal(size=(8, 2)), rng.normal(size=2))),
                      60, 10)
    model.save(tmp_path / "model.npz")
    back = GainModel.load(tmp_path / "model.npz")
    x = rng.normal(size=(4, F))
    np.testing.assert_array_equal(back.evaluate(x), model.evaluate(x))
    meta = json.loads((tmp_path / "model.json").read_text())
    meta["features"] = meta["features"][:-1]
    (tmp_path / "model.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="team features"):
        GainModel.load(tmp_path / "model.npz")
    with pytest.raises(FileNotFoundError, match="no such file"):
        GainModel.load(tmp_path / "missing.npz")


@pytest.mark.parametrize("spec, measure", [("per_anchor_drift:0.15", "drift"), ("per_anchor_threshold:0.15", "total")])
def test_without_a_departure_it_is_the_rule(spec, measure):
    rule, _ = run(make_policy(spec))
    distilled, _ = run(DistilledPolicy(constant_model(0.5, 0.5), margin=1.0, base_threshold_m=0.15,
                                       base_measure=measure))
    assert distilled == rule
    assert any(v for step in rule for v in step.values())  # the rule did act in this episode


def test_departs_at_decision_points_only_when_no_round_runs():
    policy = DistilledPolicy(constant_model(team=1.0, wait=-1.0, decide=2), margin=0.5, base_threshold_m=10.0,
                             base_measure="drift")  # a rule that never asks
    actions, _ = run(policy, max_cycles=40)
    team_steps = [t + 1 for t, a in enumerate(actions) if all(v == TEAM_ROUND for v in a.values())]
    assert team_steps and all(t % 2 == 0 for t in team_steps)
    assert policy.decisions["team"] == len(team_steps)
    assert len(team_steps) < 40 // 2  # the decision points inside a running round were skipped


def test_holding_off_silences_the_rule_until_the_next_decision():
    policy = DistilledPolicy(constant_model(team=-1.0, wait=1.0, decide=5), margin=0.5, base_threshold_m=0.05,
                             base_measure="drift")
    rule = make_policy("per_anchor_drift:0.05")
    config = EnvConfig.from_dict({"action_mode": "per_anchor", "max_cycles": 120})
    env = UWBCalibrationParallelEnv(config)
    policy.configure(config)
    policy.reset(0)
    obs, infos = env.reset(seed=0)
    waits, silenced = [], 0
    while env.agents:
        before = policy.decisions["wait"]
        act = policy.act(obs, infos)
        if policy.decisions["wait"] > before:
            waits.append(policy.t)
        held = any(0 < policy.t - w < 5 for w in waits)
        if held or policy.t in waits:
            assert not any(act.values())
            silenced += any(rule.act(obs, infos).values())
        obs, _, _, _, infos = env.step(act)
    assert waits and all(t % 5 == 0 for t in waits)
    assert silenced  # the rule did ask during a hold


def test_bad_parameters_are_typed_errors():
    with pytest.raises(ValueError, match="base_threshold_m"):
        DistilledPolicy(constant_model(0, 0), margin=0.1, base_threshold_m=0.0)
    with pytest.raises(ValueError, match="margin"):
        DistilledPolicy(constant_model(0, 0), margin=float("nan"), base_threshold_m=0.2)
    never = DistilledPolicy(constant_model(5.0, 5.0), margin=float("inf"), base_threshold_m=0.15, base_measure="drift")
    assert run(never)[0] == run(make_policy("per_anchor_drift:0.15"))[0]  # +inf: never depart
    with pytest.raises(ValueError, match="measure"):
        DistilledPolicy(constant_model(0, 0), margin=0.1, base_threshold_m=0.2, base_measure="mean")


def test_training_end_to_end_resumes_and_loads_through_the_registry(tmp_path):
    args = train_distilled.Args(seed=0, out=str(tmp_path / "run"), episodes=2, workers=1, n_futures=2,
                                horizon_steps=20, val_seeds=1, val_scenarios=("default", "three_anchors"),
                                max_cycles=40, hp=["max_epochs=5", "hidden=[8]"])
    summary = train_distilled.main(args)
    out = tmp_path / "run"
    assert summary["episodes"] == 2 and summary["steps"] > 0
    run_record = json.loads((out / "run.json").read_text())
    tuned_base = json.loads(train_distilled.LEARNED_BASES.read_text())["base"]["default"]  # e.g. drift:0.3
    assert run_record["env"] == "distilled" and run_record["base"] == tuned_base
    assert set(run_record["validation"]["relative_gain"]) >= {"rule", "0"}
    assert run_record["validation"]["relative_gain"]["rule"] == 0.0
    data = sorted((out / "data").glob("ep*.npz"))
    assert [p.stem for p in data] == ["ep1000", "ep1001"]  # training seeds 1000 + seed * episodes
    stamp = data[0].stat().st_mtime_ns
    train_distilled.main(args)  # resumes: the collected episodes are not run again
    assert data[0].stat().st_mtime_ns == stamp
    policy = make_policy(f"learned:{out / 'model.npz'}@0.3")
    assert isinstance(policy, DistilledPolicy) and policy.base_measure == "total" and policy.base_threshold_m == 0.3
    default = make_policy(f"learned:{out / 'model.npz'}")
    assert (default.base_measure, default.base_threshold_m) == parse_base(tuned_base)
    assert len(MOVES) == default.model.evaluate(np.zeros(F)).shape[-1]


@pytest.mark.parametrize("base", ["team:1", "drift:0.15"])
def test_validation_runs_each_rule_as_the_benchmark_does(tmp_path, base):
    """The margin is chosen against the rule as the benchmark runs it: the team threshold rule
    with team requests (in per_anchor mode its 1s would be re-location requests)."""
    from uwb_env.training.evaluate import run_episode
    from uwb_env.training.suite import load_suite

    constant_model(5.0, 5.0).save(tmp_path / "model.npz")
    sc = load_suite()["fast_robots"]
    config = {**sc["config"], "max_cycles": 60}
    bench = run_episode(base_spec(base), 500_000, config)["return"]
    rule = train_distilled._validation_episode((str(tmp_path / "model.npz"), None, base, "fast_robots", 500_000, 60))
    never = train_distilled._validation_episode((str(tmp_path / "model.npz"), float("inf"), base, "fast_robots",
                                                 500_000, 60))
    assert rule[3] == bench == never[3]


def test_a_team_base_is_recorded_as_team_rounds():
    """The team threshold rule runs in its own (binary) action mode; its requests are recorded
    as the team rounds the deployed policy's rule gives (features agree between the two)."""
    ep = train_distilled.collect_episode((500_000, "fast_robots", "team:0.3", 10, 2, 5, 40))
    recorded = np.concatenate([r[1] for r in ep["rows"]])
    assert set(recorded.tolist()) == {0, TEAM_ROUND}


def test_recorded_features_are_what_the_deployed_policy_computes():
    seed, config = 7, {"max_cycles": 40}
    ep = train_distilled.collect_episode((seed, "default", "drift:0.2121", 10, 2, 5, 40))
    assert [r[5] for r in ep["rows"]] == ["base"] * len(ep["rows"])  # the rollout kept to the rule here
    seen = []

    class Spy(GainModel):
        def evaluate(self, features):
            seen.append(np.array(features))
            return np.full(len(MOVES), -1e9)

    spy = Spy(np.zeros(F), np.ones(F), ((np.zeros((F, 2)), np.zeros(2)),), 10, 5)
    policy = DistilledPolicy(spy, margin=0.0, base_threshold_m=0.2121, base_measure="drift")
    from uwb_env.training.evaluate import run_policy_episode

    run_policy_episode(policy, seed, {**config, "action_mode": "per_anchor"})
    recorded = [team_features(r[0], r[1], 0.2121, 0.2, 40 - r[6], 10) for r in ep["rows"]]
    assert len(seen) == len(recorded) > 3
    for a, b in zip(seen, recorded, strict=True):
        np.testing.assert_array_equal(a, b)


def test_gain_targets_zero_only_moves_that_were_not_simulated():
    base = np.array([[1.0, 2.0], [1.0, 2.0]])
    np.testing.assert_array_equal(train_distilled._gains(np.array([[np.nan, np.nan], [2.0, 4.0]]), base), [0.0, 1.5])
    with pytest.raises(ValueError, match="non-finite"):
        train_distilled._gains(np.array([[np.nan, 3.0]]), base[:1])


def test_collection_refuses_to_resume_with_other_settings(tmp_path):
    args = train_distilled.Args(seed=0, out=str(tmp_path), episodes=1, workers=1, n_futures=2, horizon_steps=10,
                                decide_every_steps=5, max_cycles=20)
    assert len(train_distilled.collect(args, "drift:0.2121", tmp_path)) == 1
    manifest = json.loads((tmp_path / "data" / "manifest.json").read_text())
    assert manifest["collect_wall_s"] > 0 and manifest["n_futures"] == 2
    with pytest.raises(ValueError, match="collected with"):
        train_distilled.collect(train_distilled.Args(**{**args.__dict__, "n_futures": 3}), "drift:0.2121", tmp_path)


def test_fit_needs_two_episodes_and_cuts_features_the_data_never_varied():
    rng = np.random.default_rng(0)
    X = rng.normal(size=(40, F))
    X[:, TEAM_FEATURES.index("n_anchors")] = 4.0
    Y = rng.normal(size=(40, 2))
    hp = {"hidden": [8], "learning_rate": 1e-2, "weight_decay": 0.0, "batch_size": 16, "max_epochs": 3, "patience": 2}
    with pytest.raises(ValueError, match="at least 2"):
        train_distilled.fit_gain_model(X, Y, np.zeros(40, int), hp, 0, 60, 10)
    model, _ = train_distilled.fit_gain_model(X, Y, np.arange(40) % 5, hp, 0, 60, 10)
    x = X[0].copy()
    x16 = x.copy()
    x16[TEAM_FEATURES.index("n_anchors")] = 16.0
    np.testing.assert_array_equal(model.evaluate(x16), model.evaluate(x))


def test_gain_model_shapes_are_checked():
    with pytest.raises(ValueError, match="mean/scale"):
        GainModel(np.zeros(F - 1), np.ones(F - 1), ((np.zeros((F, 2)), np.zeros(2)),), 60, 10)
    with pytest.raises(ValueError, match="outputs"):
        GainModel(np.zeros(F), np.ones(F), ((np.zeros((F, 3)), np.zeros(3)),), 60, 10)
    with pytest.raises(ValueError, match="decide_every_steps"):
        GainModel(np.zeros(F), np.ones(F), ((np.zeros((F, 2)), np.zeros(2)),), 60, 0)
