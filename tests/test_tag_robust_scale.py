"""The tag tracker's own robust scale (``solver.tag_f_scale_sigmas``): a stale anchor's biased
range lies within a few of its predicted stds, so only a scale near one predicted std
down-weighs it; calibrations do not read it."""

import numpy as np
import pytest

import uwb_env
from uwb_env.config import ConfigError, EnvConfig
from uwb_env.localization.multilateration import track_tags_2d


def test_a_stale_anchor_is_down_weighted_only_at_a_scale_near_its_predicted_std():
    anchors = np.array([[0.0, 0.0], [20.0, 0.0], [20.0, 20.0], [0.0, 20.0], [10.0, -5.0]])
    tag = np.array([[8.0, 7.0]])
    ranges = np.linalg.norm(tag[:, None] - anchors[None], axis=-1)
    ranges[0, 2] += 0.6  # anchor 2 has drifted 0.6 m along the line of sight: a bias, not noise
    cov = np.repeat(np.eye(2)[None] * 0.15**2, len(anchors), axis=0)  # every anchor predicted at 0.15 m per axis
    errors = {}
    for loss, scale in (("huber", 3.0), ("huber", 1.0), ("linear", 1.0)):
        fix, _, _ = track_tags_2d(anchors[None], tag[None], ranges[None], 0.1**2, cov[None], loss, scale, 20)
        errors[loss, scale] = float(np.linalg.norm(fix[0, 0] - tag[0]))
    # 3 predicted stds (0.54 m along any line of sight) take the bias for noise: plain least squares
    assert errors["huber", 3.0] == pytest.approx(errors["linear", 1.0], rel=1e-9)
    assert errors["huber", 1.0] < 0.6 * errors["huber", 3.0]


# NLOS-biased ranges: the calibrations' robust loss has outliers to down-weigh, so its scale
# moves the anchors (the control below); a team round every 10 steps. Six anchors in the env
# tests: four in 3D leave no redundant pair (every residual is zero, no loss matters), one in 2D.
NLOS = {"ranging": {"nlos_probability": 0.3}}


@pytest.mark.parametrize("dim", [2, 3])
def test_the_env_fixes_tags_with_the_tag_scale_and_calibrates_with_the_other(dim):
    def trace(solver: dict) -> tuple[np.ndarray, np.ndarray]:
        env = uwb_env.parallel_env(sim={"dim": dim, "n_anchors": 6, **NLOS}, solver=solver, max_cycles=60)
        env.reset(seed=3)
        system = env.unwrapped.system
        anchors, fixes = [system.world.anchors_est.copy()], []
        for t in range(60):
            env.step({a: int(t % 10 == 9) for a in env.agents})
            anchors.append(system.world.anchors_est.copy())
            fixes.append(system.state.tag_fix[0].copy())
        return np.array(anchors), np.array(fixes)

    anchors, fixes = trace({"tag_f_scale_sigmas": 3.0})
    tag_anchors, tag_fixes = trace({"tag_f_scale_sigmas": 0.5})
    cal_anchors, _ = trace({"tag_f_scale_sigmas": 3.0, "f_scale_sigmas": 0.5})
    assert system_calibrated(anchors)
    # the calibrations do not read the tag scale: the same anchors at every step ...
    np.testing.assert_array_equal(anchors, tag_anchors)
    # ... while they do read theirs (the control) and the tag fixes read the tag scale
    assert not np.allclose(anchors, cal_anchors)
    assert np.isfinite(fixes).any() and not np.allclose(fixes, tag_fixes, equal_nan=True)


def system_calibrated(anchors: np.ndarray) -> bool:
    """Some step after the reset moved the estimates by more than odometry does (a calibration)."""
    return bool((np.abs(np.diff(anchors, axis=0)).max(axis=(1, 2)) > 0.05).any())


@pytest.mark.parametrize("value", [0.0, -1.0, float("nan")])
def test_a_bad_tag_scale_names_the_field(value):
    with pytest.raises(ConfigError) as err:
        EnvConfig.from_dict({"solver": {"tag_f_scale_sigmas": value}})
    assert err.value.field == "solver.tag_f_scale_sigmas"


def test_the_batched_env_fixes_tags_with_the_tag_scale_and_calibrates_with_the_other():
    from uwb_env.batch import BatchedSystem

    def trace(solver: dict) -> tuple[np.ndarray, np.ndarray]:
        system = BatchedSystem(EnvConfig.from_dict({"sim": {"n_anchors": 6, **NLOS}, "solver": solver}), 4)
        system.reset(np.random.default_rng(5))
        anchors, fixes = [system.anchors_est.copy()], []
        for t in range(40):
            system.step(np.full(4, t % 10 == 9))
            anchors.append(system.anchors_est.copy())
            fixes.append(system.state.tag_fix.copy())
        return np.array(anchors), np.array(fixes)

    anchors, fixes = trace({"tag_f_scale_sigmas": 3.0})
    tag_anchors, tag_fixes = trace({"tag_f_scale_sigmas": 0.5})
    cal_anchors, _ = trace({"tag_f_scale_sigmas": 3.0, "f_scale_sigmas": 0.5})
    np.testing.assert_array_equal(anchors, tag_anchors)
    assert not np.allclose(anchors, cal_anchors)
    assert np.isfinite(fixes).any() and not np.allclose(fixes, tag_fixes, equal_nan=True)
