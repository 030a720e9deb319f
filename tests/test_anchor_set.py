"""The team-size-invariant per-anchor scheduler: features, training env, training run, policy."""

import json
from pathlib import Path

import numpy as np
import pytest
from uwb_env.agents.anchor_set import ANCHOR_SET_FIELDS, N_FEATURES, anchor_set_features, from_observations

from uwb_env.system import OBS_FIELDS


def _reference(own: np.ndarray, dt: float, threshold: float = 0.3) -> np.ndarray:
    """Row by row, with explicit loops over the other anchors; the base action counted by hand."""
    n = own.shape[0]
    stale = own[:, 1] > threshold
    team = stale.sum() >= 0.5 * n
    rows = []
    for i in range(n):
        others = np.delete(own, i, axis=0)[:, :6]
        rank = np.mean(np.delete(own[:, 1], i) < own[i, 1])
        base = np.zeros(3)
        base[2 if team else int(stale[i])] = 1.0
        rows.append(np.concatenate([own[i], others.mean(0), others.max(0), [rank, n, dt, threshold,
                                                                           own[i, 1] / threshold], base]))
    return np.array(rows)


@pytest.mark.parametrize("n", [2, 3, 5, 16])
def test_features_match_a_loop_over_the_others(rng, n):
    own = rng.uniform(0, 2, (n, len(OBS_FIELDS)))
    own[1:3, 2] = own[0, 2]  # ties in the max
    for threshold in (0.3, 1.1, 1.7):  # a majority stale (team round), some, few
        got = anchor_set_features(own, 0.2, threshold)
        assert got.shape == (n, N_FEATURES) == (n, len(ANCHOR_SET_FIELDS)) and got.dtype == np.float32
        np.testing.assert_allclose(got, _reference(own, 0.2, threshold), rtol=1e-6)


def test_features_are_permutation_equivariant_and_batch(rng):
    own = rng.uniform(0, 2, (6, len(OBS_FIELDS)))
    perm = rng.permutation(6)
    np.testing.assert_allclose(anchor_set_features(own[perm], 0.5), anchor_set_features(own, 0.5)[perm])
    batch = rng.uniform(0, 2, (3, 4, len(OBS_FIELDS)))
    np.testing.assert_allclose(anchor_set_features(batch, 0.2)[1], anchor_set_features(batch[1], 0.2))
    with pytest.raises(ValueError, match="at least 2 anchors"):
        anchor_set_features(own[:1], 0.2)


@pytest.mark.parametrize("overrides", [{"sim": {"n_anchors": 3}}, {"sim": {"n_anchors": 8, "n_tags": 4}},
                                       {"sim": {"dim": 3}}])
def test_features_from_the_env_drop_positions(overrides):
    import uwb_env

    env = uwb_env.parallel_env(action_mode="per_anchor", **overrides)
    obs, _ = env.reset(seed=3)
    agents, rows = from_observations(obs, env.config.sim.dt_s)
    assert agents == env.agents and rows.shape == (env.config.sim.n_anchors, N_FEATURES)
    np.testing.assert_allclose(rows[:, : len(OBS_FIELDS)], np.stack([obs[a][-len(OBS_FIELDS):] for a in agents]))


def _distribution(tmp_path, team_sizes=(3, 5)):
    import yaml
    from uwb_env.training.train_anchor_set import DEFAULT_DISTRIBUTION, ScenarioDistribution

    raw = yaml.safe_load(Path(DEFAULT_DISTRIBUTION).read_text())
    raw.update(team_sizes=list(team_sizes), episode_s=4.0)
    path = tmp_path / "dist.yml"
    path.write_text(yaml.safe_dump(raw))
    return path, ScenarioDistribution.load(path)


def test_distribution_refuses_unknown_keys_and_small_teams(tmp_path):
    from uwb_env.training.train_anchor_set import ScenarioDistribution

    path, _ = _distribution(tmp_path)
    text = path.read_text()
    (tmp_path / "bad.yml").write_text(text + "wind_mps: [0, 1]\n")
    with pytest.raises(ValueError, match="unknown keys \\['wind_mps'\\]"):
        ScenarioDistribution.load(tmp_path / "bad.yml")
    (tmp_path / "small.yml").write_text(text.replace("team_sizes:\n- 3\n- 5", "team_sizes:\n- 2\n- 5"))
    with pytest.raises(ValueError, match="team_sizes"):
        ScenarioDistribution.load(tmp_path / "small.yml")


def test_vec_env_slots_rewards_and_episode_ends(tmp_path):
    from uwb_env.training.vec_env import AnchorSetVecEnv

    _, dist = _distribution(tmp_path)
    venv = AnchorSetVecEnv(dist, np.random.default_rng(0), seed_base=499_998, seed_span=500_000)
    obs = venv.reset()
    assert venv.num_envs == 8 and obs.shape == (8, N_FEATURES)
    col = {f: i for i, f in enumerate(ANCHOR_SET_FIELDS)}
    assert np.all(obs[:3, col["n_anchors"]] == 3) and np.all(obs[3:, col["n_anchors"]] == 5)
    # one base threshold per copy and episode, inside the distribution's range
    thr = obs[:, col["base_threshold_m"]]
    assert len(set(thr[:3])) == 1 and len(set(thr[3:])) == 1 and np.all((thr >= 0.1) & (thr <= 1.0))
    assert np.all(obs[:, -3:].sum(1) == 1)  # the base action's one-hot
    ended = 0
    for _ in range(40):
        obs, rew, dones, infos = venv.step(np.zeros(8, dtype=int))
        assert rew[0] == rew[1] == rew[2] and rew[3] == rew[7]  # the team reward in every slot of a copy
        if dones.any():
            assert dones[:3].all() == dones[0] and dones[3:].all() == dones[3]
            k = int(np.flatnonzero(dones)[0])
            assert infos[k]["TimeLimit.truncated"] and infos[k]["terminal_observation"].shape == (N_FEATURES,)
            ended += dones.sum()
    assert ended > 0
    assert venv.episodes > 2 and all(e.config.action_mode == "per_anchor" for e in venv.envs)


def test_training_runs_saves_a_validation_chosen_model_and_resumes(tmp_path):
    from uwb_env.training.train_anchor_set import Args, main

    path, _ = _distribution(tmp_path, team_sizes=(3, 4))
    args = Args(seed=1, out=str(tmp_path / "run"), total_timesteps=3000, eval_every_steps=1500, distribution=str(path),
                hp=["n_steps=64", "batch_size=224"], val_episodes_per_scenario=1, val_max_cycles=20, max_wall_s=None)
    first = main(args)
    assert first["steps"] >= 3000 and len(first["history"]) >= 2
    best = tmp_path / "run" / "best"
    assert (best / "model.zip").is_file() and (best / "vecnormalize.pkl").is_file()
    record = json.loads((best / "run.json").read_text())
    assert record["env"] == "anchor_set" and record["val_return"] == max(h["val_return"] for h in first["history"])
    state = tmp_path / "run" / "checkpoints" / "state.json"
    episodes_before = json.loads(state.read_text())["episodes"]
    # the same command after the end (or a kill) continues from the checkpoint: no steps lost,
    # and the scenario stream goes on where it stopped instead of replaying its start
    again = main(Args(**{**args.__dict__, "total_timesteps": 4500}))
    assert again["steps"] >= 4500 and len(again["history"]) > len(first["history"])
    assert json.loads(state.read_text())["episodes"] > episodes_before
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("mine")
    with pytest.raises(FileExistsError, match="refusing"):
        main(Args(**{**args.__dict__, "out": str(tmp_path / "other")}))

    # the trained model runs on any team size, 2D or 3D, through the registry's learned: spec
    from uwb_env.training.evaluate import run_episode

    for overrides in ({"sim": {"n_anchors": 3}}, {"sim": {"n_anchors": 16, "n_tags": 2, "area_size_m": 30.0}},
                      {"sim": {"dim": 3}}):
        ep = run_episode(f"learned:{best / 'model.zip'}", 1_000_000, {**overrides, "max_cycles": 15})
        assert np.isfinite(ep["mean_tag_error_m"]) and len(ep["tag_error_trace"]) == 15


def test_numpy_actor_takes_the_same_actions_as_sb3():
    pytest.importorskip("stable_baselines3")
    from uwb_env.agents.anchor_set import _argmax_logits
    from uwb_env.agents.registry import make_policy

    policy = make_policy("learned:anchor_set")
    assert policy._layers is not None
    rng = np.random.default_rng(0)
    x = rng.normal(0, 2, (5000, N_FEATURES)).astype(np.float32)
    x[:, -3:] = np.eye(3)[rng.integers(0, 3, 5000)]  # the base action's one-hot, as the features give it
    sb3, _ = policy.policy.predict(x, deterministic=True)
    assert policy.prior_logit > 0  # the shipped model is a residual over the rule
    np.testing.assert_array_equal(_argmax_logits(policy._layers, x, policy.prior_logit), sb3)
    assert len(np.unique(sb3)) == 3  # the inputs exercise every action


@pytest.mark.parametrize("threshold,measure", [(0.1, "total"), (0.3, "total"), (0.1, "drift"), (0.2, "team")])
def test_an_untrained_residual_policy_is_the_per_anchor_threshold_rule(tmp_path, threshold, measure):
    """The residual starts as its base rule, exactly (argmax), in the numpy actor and in SB3. On
    the team measure it is ``threshold:T`` as the harness runs it (the centralized action)."""
    pytest.importorskip("stable_baselines3")
    from stable_baselines3 import PPO
    from uwb_env.agents.anchor_set import AnchorSetPolicy
    from uwb_env.agents.per_anchor import PerAnchorThresholdPolicy
    from uwb_env.agents.prior_policy import PartialVecNormalize, PriorLogitsPolicy
    from uwb_env.env.policy import rollout
    from uwb_env.training.vec_env import AnchorSetVecEnv

    import uwb_env

    _, dist = _distribution(tmp_path, team_sizes=(3, 4))
    venv = PartialVecNormalize(AnchorSetVecEnv(dist, np.random.default_rng(0), 0, 500_000))
    model = PPO(PriorLogitsPolicy, venv, n_steps=8, batch_size=8, seed=0, device="cpu",
                policy_kwargs={"prior_logit": 3.0})
    venv.reset()
    for _ in range(30):  # statistics far from the identity: the one-hot must still pass raw
        venv.step(np.zeros(venv.num_envs, dtype=int))
    obs, *_ = venv.step(np.zeros(venv.num_envs, dtype=int))
    onehot = np.eye(3)[obs[:, -3:].argmax(1)]
    np.testing.assert_array_equal(obs[:, -3:], onehot)  # the venv's normalized output keeps the one-hot raw
    assert np.abs(obs[:, :-3]).max() > 0 and not np.allclose(venv.obs_rms.mean[-3:], 0)  # others normalized
    learned = AnchorSetPolicy(model.policy, venv.obs_rms, venv.clip_obs, base_threshold_m=threshold,
                              base_measure=measure)
    assert learned.prior_logit == 3.0 and learned._layers is not None
    env = uwb_env.parallel_env(max_cycles=120, action_mode="per_anchor", sim={"n_anchors": 5})
    a = rollout(env, learned, seed=4)
    if measure == "team":
        from uwb_env.agents.baselines import UncertaintyThresholdPolicy

        b = rollout(uwb_env.parallel_env(max_cycles=120, sim={"n_anchors": 5}), UncertaintyThresholdPolicy(threshold),
                    seed=4)
    else:
        b = rollout(env, PerAnchorThresholdPolicy(threshold, measure=measure), seed=4)
    np.testing.assert_array_equal(a.round_started, b.round_started)
    np.testing.assert_array_equal(a.tag_error_m, b.tag_error_m)
    assert a.round_started.any()  # the rule calibrates in these episodes
    # SB3's own deterministic prediction agrees with the numpy actor
    obs, _ = env.reset(seed=4)
    for _ in range(40):
        agents, rows = learned.rows(obs)
        np.testing.assert_array_equal(rows[:, -3:], np.eye(3)[rows[:, -3:].argmax(1)])  # raw here too
        sb3, _ = model.policy.predict(rows, deterministic=True)
        np.testing.assert_array_equal(sb3, np.argmax(rows[:, -3:], axis=1))
        obs, *_ = env.step(learned.act(obs, {}))
    venv.close()


def test_team_round_requests_are_votes():
    from uwb_env.agents.per_anchor import NOTHING, RELOCATE_ME, TEAM_ROUND, team_vote

    lone = np.array([TEAM_ROUND, RELOCATE_ME, NOTHING, NOTHING, NOTHING])
    np.testing.assert_array_equal(team_vote(lone), [NOTHING, RELOCATE_ME, NOTHING, NOTHING, NOTHING])
    half = np.array([[TEAM_ROUND, TEAM_ROUND, RELOCATE_ME, NOTHING], [TEAM_ROUND, NOTHING, NOTHING, NOTHING]])
    np.testing.assert_array_equal(team_vote(half), [half[0], [NOTHING] * 4])  # per team, on a batch


def test_the_deployed_policy_casts_team_requests_as_votes():
    from uwb_env.agents.anchor_set import AnchorSetPolicy
    from uwb_env.agents.per_anchor import NOTHING, TEAM_ROUND

    policy = AnchorSetPolicy(policy=None)  # no SB3 model: a hand-made actor below
    w = np.zeros((N_FEATURES, 3))
    w[ANCHOR_SET_FIELDS.index("predicted_position_std_m"), TEAM_ROUND] = 1.0  # team logit = own std
    policy._layers = [[w, np.array([0.5, -1.0, 0.0]), False]]  # "nothing" logit 0.5
    obs = {f"anchor_{i}": np.r_[0.0, 0.0, 1.0, s, np.zeros(len(OBS_FIELDS) - 2)].astype(np.float32)
           for i, s in enumerate([0.9, 0.1, 0.1, 0.1])}
    assert set(policy.act(obs, {}).values()) == {NOTHING}  # one vote of four: no team round
    obs["anchor_1"][3] = 0.8  # two of four: the quorum
    assert set(policy.act(obs, {}).values()) == {TEAM_ROUND, NOTHING} and policy.act(obs, {})["anchor_0"] == TEAM_ROUND


def test_training_copies_cast_team_requests_as_votes(tmp_path):
    from uwb_env.agents.per_anchor import NOTHING, TEAM_ROUND
    from uwb_env.training.vec_env import AnchorSetVecEnv

    _, dist = _distribution(tmp_path, team_sizes=(3, 5))
    venv = AnchorSetVecEnv(dist, np.random.default_rng(0), seed_base=0, seed_span=500_000)
    venv.reset()
    calibrating = ANCHOR_SET_FIELDS.index("calibrating")
    lone = np.full(8, NOTHING)
    lone[3] = TEAM_ROUND  # one anchor of the 5-anchor copy: short of the quorum
    obs, *_ = venv.step(lone)
    assert np.all(obs[3:, calibrating] == 0)
    quorum = np.full(8, NOTHING)
    quorum[3:6] = TEAM_ROUND  # three of five
    obs, *_ = venv.step(quorum)
    assert np.all(obs[3:, calibrating] == 1) and np.all(obs[:3, calibrating] == 0)
    venv.close()


def test_the_learned_spec_names_the_base_rule():
    pytest.importorskip("stable_baselines3")
    from uwb_env.agents.registry import PolicySpecError, make_policy

    total, drift = make_policy("learned:anchor_set@0.25"), make_policy("learned:anchor_set@drift:0.4")
    assert (total.base_threshold_m, total.base_measure) == (0.25, "total")
    assert (drift.base_threshold_m, drift.base_measure) == (0.4, "drift")
    assert make_policy("learned:anchor_set@total:0.25").base_measure == "total"
    assert make_policy("learned:anchor_set@team:0.5").base_measure == "team"
    with pytest.raises(PolicySpecError, match="needs a base threshold"):
        make_policy("learned:anchor_set@drift:")
    with pytest.raises(PolicySpecError, match="must be a number"):
        make_policy("learned:anchor_set@max:0.3")


def test_the_learned_base_is_the_best_family_it_can_express():
    from uwb_env.agents.per_anchor import learned_base

    assert learned_base("per_anchor_threshold:0.3") == "0.3"
    assert learned_base("per_anchor_drift:0.25") == "drift:0.25"
    assert learned_base("threshold:1") == "team:1"
    with pytest.raises(ValueError, match="as its base"):
        learned_base("fixed:60")  # no rule of the residual's features
