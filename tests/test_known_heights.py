"""3D with the anchors' mount heights known on board (``SimConfig.known_heights_std_m``)."""

from types import SimpleNamespace

import numpy as np
import pytest

from uwb_env.config import ConfigError, EnvConfig, SimConfig
from uwb_env.env.parallel_env import UWBCalibrationParallelEnv
from uwb_env.localization.calibration import calibrate_anchors_known_heights
from uwb_env.measurements import RangeMatrix
from uwb_env.sim import World
from uwb_env.system import LocalizationSystem
from uwb_env.team_state import FIT_OK, RoundSolutions


@pytest.mark.parametrize("sim", [{"dim": 2, "known_heights_std_m": 0.02}, {"dim": 3, "known_heights_std_m": 0.0},
                                 {"dim": 3, "known_heights_std_m": -0.1}, {"dim": 3, "known_heights_std_m": "x"}])
def test_bad_values_name_the_field(sim):
    with pytest.raises(ConfigError, match="known_heights_std_m"):
        SimConfig.from_dict(sim)


def test_a_world_without_truth_refuses_simulated_heights():
    cfg = EnvConfig.from_dict({"sim": {"dim": 3, "known_heights_std_m": 0.02}})
    with pytest.raises(ConfigError, match="known_heights_std_m"):
        LocalizationSystem(cfg, world=SimpleNamespace(has_ground_truth=False))


def _episode(seed: int, known: float | None, steps: int):
    sim = {"dim": 3} if known is None else {"dim": 3, "known_heights_std_m": known}
    env = UWBCalibrationParallelEnv(EnvConfig.from_dict({"max_cycles": steps, "action_mode": "per_anchor", "sim": sim}))
    env.reset(seed=seed)
    return env


def test_the_placement_and_per_episode_draws_stay_where_they_were():
    worlds = {}
    for known in (None, 0.02):
        world = World(SimConfig.from_dict({"dim": 3, "known_heights_std_m": known}))
        world.reset(np.random.default_rng(7))
        worlds[known] = world
    plain, known = worlds[None], worlds[0.02]
    np.testing.assert_array_equal(plain.anchors_true, known.anchors_true)
    np.testing.assert_array_equal(plain.tags_true, known.tags_true)
    assert plain.known_heights_m is None
    err = known.known_heights_m - known.anchors_true[:, 2]
    assert 0 < np.abs(err).max() < 0.1  # told with an error of the configured size


def _worst_height_error(env, steps: int) -> float:
    """Largest |estimated - true| anchor height in the estimate frame over ``steps`` steps of
    relocations (action 1 for one anchor in turn) and a team round every 25 steps."""
    s, worst = env.system, 0.0
    agents = list(env.agents)
    for t in range(steps):
        actions = {a: 0 for a in agents}
        actions[agents[t % len(agents)]] = 1 if t % 5 == 0 else 0
        if t % 25 == 12:
            actions = {a: 2 for a in agents}
        env.step(actions)
        truth = s.world.to_estimate_frame(s.world.anchors_true)
        worst = max(worst, float(np.abs(s.world.anchors_est[:, 2] - truth[:, 2]).max()))
    return worst


def test_known_heights_hold_through_relocations_and_team_rounds():
    """three_d test seed 1,000,058: without the heights the team's shape collapses flat (height
    errors of a metre and more); with them every calibration keeps each anchor's height."""
    known = _episode(1_000_058, 0.02, 400)
    rot = known.system.world.frame_rotation
    np.testing.assert_allclose(rot[2], [0.0, 0.0, 1.0])  # the frame keeps the vertical
    np.testing.assert_allclose(rot[:2, 2], [0.0, 0.0])
    assert _worst_height_error(known, 400) < 0.1
    assert known.system.anchor_round_count > 10 and known.system.calibration_count > 5
    unknown = _episode(1_000_058, None, 400)
    assert _worst_height_error(unknown, 400) > 0.5  # the control: the ranges alone lose the heights


def test_relocations_keep_the_known_height():
    """Relocations alone (no team round): each takes the anchor's known height as a sharp prior,
    so the estimated heights stay on the known ones (without that prior they wander 0.2-0.6 m
    over 400 steps on these seeds)."""
    for seed in (1_000_001, 7):
        env = _episode(seed, 0.02, 200)
        s, agents = env.system, list(env.agents)
        for t in range(200):
            env.step({a: int(k == t % len(agents) and t % 5 == 0) for k, a in enumerate(agents)})
        assert s.anchor_round_count >= 30
        np.testing.assert_allclose(s.world.anchors_est[:, 2], s.world.known_heights_m, atol=0.01)


def test_planar_solutions_take_the_heights_as_given():
    planar = RoundSolutions(2, 3, 2)
    planar.fit[:] = FIT_OK
    planar.positions[:] = np.arange(12.0).reshape(2, 3, 2)
    planar.anchor_cov[:] = 0.01 * np.eye(2)
    lifted = planar.with_heights(np.array([[1.0, 2.0, 3.0], [0.5, 0.5, 0.5]]), 0.03)
    assert lifted.positions.shape == (2, 3, 3) and (lifted.fit == FIT_OK).all()
    np.testing.assert_array_equal(lifted.positions[1, :, 2], [0.5, 0.5, 0.5])
    np.testing.assert_allclose(lifted.anchor_cov[0, 1], np.diag([0.01, 0.01, 0.0009]))
    with pytest.raises(ValueError, match="planar"):
        lifted.with_heights(np.zeros((2, 3)), 0.03)


def test_known_heights_keep_the_planes_own_verdict_when_asked():
    xy = np.array([[0.0, 0.0], [8.0, 0.0], [7.0, 6.0], [1.0, 7.0]])
    z = np.array([0.5, 2.0, 1.0, 2.5])
    d = np.linalg.norm(np.column_stack([xy, z])[:, None] - np.column_stack([xy, z])[None], axis=-1)
    count = np.full((4, 4), 5) - 5 * np.eye(4, dtype=int)
    rm = RangeMatrix(np.where(np.eye(4, dtype=bool), np.nan, d), np.full((4, 4), 0.05), count)
    fallback = calibrate_anchors_known_heights(rm, z, 0.02)
    given = calibrate_anchors_known_heights(rm, z, 0.02, mark_ambiguous=False)
    assert fallback.ambiguous and not given.ambiguous
    np.testing.assert_allclose(given.positions[:, 2], z)
