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


@pytest.mark.parametrize("dim", [2, 3])
def test_the_env_fixes_tags_with_the_tag_scale_and_not_its_calibrations(dim):
    def trace(solver: dict) -> tuple[np.ndarray, list]:
        env = uwb_env.parallel_env(sim={"dim": dim}, solver=solver, max_cycles=40)
        env.reset(seed=3)
        anchors_after_reset = env.unwrapped.system.world.anchors_est.copy()
        fixes = []
        for _ in range(40):
            env.step({a: 0 for a in env.agents})
            fixes.append(env.unwrapped.system.state.tag_fix[0].copy())
        return anchors_after_reset, fixes

    base, base_fixes = trace({"tag_f_scale_sigmas": 3.0})
    tags_only, tag_fixes = trace({"tag_f_scale_sigmas": 0.5})
    # the first calibration does not read the tag scale: the same anchors
    np.testing.assert_array_equal(base, tags_only)
    # ... and the tag fixes read the tag scale
    assert any(not np.allclose(a, b, equal_nan=True) for a, b in zip(base_fixes, tag_fixes, strict=True))


@pytest.mark.parametrize("value", [0.0, -1.0, float("nan")])
def test_a_bad_tag_scale_names_the_field(value):
    with pytest.raises(ConfigError) as err:
        EnvConfig.from_dict({"solver": {"tag_f_scale_sigmas": value}})
    assert err.value.field == "solver.tag_f_scale_sigmas"


def test_the_batched_env_fixes_tags_with_the_tag_scale():
    from uwb_env.batch import BatchedSystem

    def fixes(scale: float) -> np.ndarray:
        system = BatchedSystem(EnvConfig.from_dict({"solver": {"tag_f_scale_sigmas": scale}}), 4)
        system.reset(np.random.default_rng(5))
        out = []
        for _ in range(30):
            system.step(np.zeros(4, dtype=bool))
            out.append(system.state.tag_fix.copy())
        return np.array(out)

    base, other = fixes(3.0), fixes(0.5)
    assert np.isfinite(base).any() and not np.allclose(base, other, equal_nan=True)
