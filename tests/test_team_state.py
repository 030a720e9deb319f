"""The state both systems share (uwb_env.team_state): tag tracks through a round, and the
calibration update."""

import numpy as np
import pytest

from uwb_env.batch import BatchedSystem
from uwb_env.config import EnvConfig
from uwb_env.system import LocalizationSystem
from uwb_env.team_state import FIT_OK, FIT_POOR, RoundSolutions, TeamState

PREDICT = EnvConfig.from_dict({"tag_fallback": "predict"})


def _velocity_after_a_round(step, state, time_s, rows):
    """Step until a round has held the tags and they are fixed again; return the velocity the
    tracks report then and the one their measured fixes give ((new - last measured) / elapsed)."""
    fix_before, t_before = state.tag_fix[rows].copy(), time_s()
    held = 0
    step(True)
    while state.tag_fix_age_s[rows].max() > 0 or held == 0:
        held += 1
        assert held < 200
        step(False)
    return state.tag_velocity[rows], (state.tag_fix[rows] - fix_before) / (time_s() - t_before), held


def test_single_env_velocity_after_a_round_is_the_measured_displacement():
    # With tag_fallback="predict" the held fixes move on at the old velocity while a round
    # holds the channel; the velocity after it must come from the last *measured* fix (before:
    # the predicted one, which shrank it by the hold's share of the elapsed time).
    system = LocalizationSystem(PREDICT)
    system.reset(np.random.default_rng(2))
    for _ in range(5):
        system.step(np.zeros(system.n_anchors, dtype=bool))
    ones = np.ones(system.n_anchors, dtype=bool)
    velocity, measured, held = _velocity_after_a_round(lambda go: system.step(ones if go else ~ones), system.state,
                                                      lambda: system.world.time_s, 0)
    assert held >= 3
    np.testing.assert_allclose(velocity, measured, rtol=1e-9, atol=1e-12)


def test_batched_env_velocity_after_a_round_is_the_measured_displacement():
    system = BatchedSystem(PREDICT, 4)
    system.reset(np.random.default_rng(2))
    for _ in range(5):
        system.step(np.zeros(4, dtype=bool))
    go = np.array([True, False, False, False])
    velocity, measured, held = _velocity_after_a_round(lambda g: system.step(go if g else np.zeros(4, dtype=bool)),
                                                      system.state, lambda: system.time_s, 0)
    assert held >= 3
    np.testing.assert_allclose(velocity, measured, rtol=1e-9, atol=1e-12)


def test_apply_calibrations_scales_poor_fits_and_resets_the_clock():
    state = TeamState.new(3, 4, 2, 2, window=5)
    state.tick(0.2)
    state.hist_count[:] = 4
    anchors = np.zeros((3, 4, 2))
    sol = RoundSolutions(2, 4, 2)
    sol.positions[:] = np.arange(8.0).reshape(4, 2)
    sol.anchor_cov[:] = 0.01 * np.eye(2)
    sol.fit[:] = [FIT_OK, FIT_POOR]
    sol.chi2[:], sol.dof[:] = 40.0, 10
    sol.rms_m[:] = [0.05, 0.2]
    # team 2 takes solution 0, team 0 solution 1 (a poor fit: covariance x chi2/dof = 4)
    state.apply_calibrations(np.array([2, 0]), anchors, sol, np.array([0, 1]), np.full((2, 4, 2), 0.5))
    np.testing.assert_allclose(anchors[2], sol.positions[0] + 0.5)
    np.testing.assert_allclose(anchors[1], 0.0)  # untouched
    np.testing.assert_allclose(state.calibration_var_m2[2], 0.02)
    np.testing.assert_allclose(state.calibration_var_m2[0], 0.08)
    assert state.calibration_count.tolist() == [1, 0, 1]
    assert state.calibrations_poor_fit.tolist() == [1, 0, 0]
    assert state.last_calibration_rms_m.tolist() == [0.2, 0.0, 0.05]
    assert state.time_since_calibration_s[1].tolist() == pytest.approx([0.2] * 4)
    assert state.time_since_calibration_s[[0, 2]].max() == 0.0
    assert state.hist_count.tolist() == [0, 4, 0]


def test_a_step_without_a_fix_is_not_a_measurement():
    # A tag that misses its fix on an ordinary step (dropouts) keeps its last fix, unmoved; the
    # next measured fix's velocity is over the time since the last measured one (a review
    # found the predicted-fix correction applied to such steps: 3.5 m/s instead of 1.0 here).
    state = TeamState.new(1, 4, 1, 2, window=10)
    none, stats, ok = np.zeros(1), np.zeros((1, 4)), np.ones(1, dtype=bool)

    def record(position, rms):
        state.record_tag_fixes(slice(None), np.array([[position]], dtype=float), np.array([[rms]]), none, stats, ok,
                               0.2)

    record([0.0, 0.0], 0.1)
    record([1.0, 0.0], 0.1)
    np.testing.assert_allclose(state.tag_velocity[0, 0], [5.0, 0.0])
    record([np.nan, np.nan], np.nan)
    np.testing.assert_allclose(state.tag_fix[0, 0], [1.0, 0.0])
    assert state.tag_fix_age_s[0, 0] == pytest.approx(0.2)
    state.hold_tags(slice(None), 0.2, predict=True)  # then a round holds it, moved on at 5 m/s
    np.testing.assert_allclose(state.tag_fix[0, 0], [2.0, 0.0])
    record([1.8, 0.0], 0.1)
    np.testing.assert_allclose(state.tag_velocity[0, 0], [(1.8 - 1.0) / 0.6, 0.0])
    np.testing.assert_allclose(state.tag_measured[0, 0], [1.8, 0.0])


def test_a_first_calibration_that_did_not_converge_still_sets_frame_and_estimates(monkeypatch):
    # The 3D known-heights fallback can end not_converged; the frame is set from its solution, so
    # the solution must be applied with it (the refactor had skipped it: estimates left in world
    # coordinates under a rotated frame, 2.6 m fixed-frame error at reset). The verdict is reported.
    import dataclasses

    from uwb_env import parallel_env

    original = LocalizationSystem._first_calibration

    def not_converged(self):
        return dataclasses.replace(original(self), status="not_converged", message="forced")

    monkeypatch.setattr(LocalizationSystem, "_first_calibration", not_converged)
    env = parallel_env(sim={"dim": 3, "n_anchors": 5})
    _, infos = env.reset(seed=0)
    info = infos["anchor_0"]
    assert env.system.calibration_count == 1 and info["calibration_fit"] == 2
    assert info["mean_anchor_error_fixed_frame_m"] < 0.5
