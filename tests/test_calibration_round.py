import numpy as np
import pytest

from uwb_env.config import CalibrationConfig, RangingConfig, SimConfig
from uwb_env.sim import RoundTiming, World


def test_duration_matches_the_paper_latencies():
    timing = RoundTiming.fit(CalibrationConfig())
    assert timing.duration_s(4, 5) == pytest.approx(0.9, rel=0.10)
    assert timing.duration_s(4, 50) == pytest.approx(2.5, rel=0.10)


def test_the_idle_time_is_spent_per_pair_as_in_the_firmware():
    """ss_init_main.c: every pair ends with an F broadcast and its 66.7 ms RX timeout, so a round
    costs n (n - 1) (idle + K exchange): 8 anchors take 56/12 of the 4-anchor round at every K
    (a per-initiator idle would give 2.3 s, not 4.2 s, at K = 5)."""
    timing = RoundTiming.fit(CalibrationConfig())
    assert timing.pair_idle_s == pytest.approx(0.0602, abs=5e-4)  # the firmware's timeout: 66.7 ms
    assert timing.exchange_s == pytest.approx(0.00296, abs=5e-5)
    for k in (5, 50):
        assert timing.duration_s(8, k) / timing.duration_s(4, k) == pytest.approx(56 / 12)
        assert timing.duration_s(16, k) / timing.duration_s(4, k) == pytest.approx(240 / 12)
    assert timing.duration_s(8, 5) == pytest.approx(4.2)


def test_schedule_order_and_counts():
    timing = RoundTiming.fit(CalibrationConfig())
    times, ini, resp = timing.schedule(4, 5)
    assert len(times) == 4 * 3 * 5
    assert np.all(np.diff(times) > 0)
    assert list(ini[:15]) == [0] * 15  # anchor 0 initiates first
    # the firmware's counter-clockwise poll order (IDs 1 -> 4, 3, 2; 2 -> 1, 4, 3; ...)
    pairs = [(int(i), int(j)) for i, j in zip(ini[::5], resp[::5], strict=True)]
    assert [(i + 1, j + 1) for i, j in pairs] == [(1, 4), (1, 3), (1, 2), (2, 1), (2, 4), (2, 3),
                                                  (3, 2), (3, 1), (3, 4), (4, 3), (4, 2), (4, 1)]
    # K exchanges back to back, then the pair's idle time; the round ends after the last one
    gaps = np.diff(times)
    assert np.allclose(gaps.reshape(-1)[np.arange(len(gaps)) % 5 != 4], timing.exchange_s)
    assert np.allclose(gaps[4::5], timing.pair_idle_s + timing.exchange_s)
    assert times[-1] == pytest.approx(timing.duration_s(4, 5) - timing.pair_idle_s)
    assert np.all(ini != resp)


def test_round_output_per_pair(rng):
    cfg = SimConfig.from_dict({"anchor_motion": {"model": "static"},
                               "ranging": {"nlos_probability": 0.0, "dropout_probability": 0.0}})
    world = World(cfg)
    world.reset(rng)
    matrix, steps = world.run_calibration_round(50)
    assert steps == int(np.ceil(world.timing.duration_s(4, 50) / cfg.dt_s - 1e-9))
    assert np.all(matrix.count[~np.eye(4, dtype=bool)] == 50)
    true = np.linalg.norm(world.anchors_true[:, None] - world.anchors_true[None], axis=-1)
    corrected = world.range_model.correct(matrix.mean_m)
    off = ~np.eye(4, dtype=bool)
    # mean of 50 ranges: error ~ sigma/sqrt(50) ~ 8 mm
    assert np.all(np.abs(corrected[off] - true[off]) < 0.05)
    assert np.all(matrix.std_m[off] > 0.02) and np.all(matrix.std_m[off] < 0.1)


def test_robots_keep_moving_during_the_round(rng):
    cfg = SimConfig(ranging=RangingConfig(nlos_probability=0.0, dropout_probability=0.0, noise_std_m=0.0),
                    anchor_motion=SimConfig().anchor_motion.replace(
                        speed_min_mps=2.0, speed_max_mps=2.0, heading_noise_std_rad_per_sqrt_s=0.0,
                        position_noise_std_m_per_sqrt_s=0.0))
    world = World(cfg)
    world.reset(rng)
    start = world.anchors_true.copy()
    matrix, _ = world.run_calibration_round(50)
    end = world.anchors_true
    d_start = np.linalg.norm(start[0] - start[3])
    d_end = np.linalg.norm(end[0] - end[3])
    measured = world.range_model.correct(matrix.mean_m[0, 3])
    assert not np.isclose(d_start, d_end, atol=0.05)
    # anchor 0 initiates first and polls anchor 3 first (the firmware's counter-clockwise
    # order), so those ranges are taken at the round's start
    assert abs(measured - d_start) < abs(measured - d_end)


def test_a_per_anchor_round_is_one_initiator_block_of_the_team_round():
    from uwb_env.config import CalibrationConfig
    from uwb_env.sim.calibration_round import CalibrationRound, RoundTiming

    timing = RoundTiming.fit(CalibrationConfig())
    team_t, team_i, team_r = timing.schedule(5, 3)
    one_t, one_i, one_r = timing.schedule(5, 3, initiators=[2])
    assert set(one_i.tolist()) == {2} and sorted(set(one_r.tolist())) == [0, 1, 3, 4]
    assert len(one_t) * 5 == len(team_t)
    # a team round is every anchor's block in turn: five per-anchor rounds take its time
    assert 5 * timing.duration_s(5, 3, n_initiators=1) == pytest.approx(timing.duration_s(5, 3))
    rnd = CalibrationRound(5, timing, 3, 10.0, initiators=[2])
    assert rnd.end_time_s == pytest.approx(10.0 + timing.duration_s(5, 3, 1)) and rnd.times_s[-1] <= rnd.end_time_s
    with pytest.raises(ValueError, match="initiators"):
        timing.schedule(5, 3, initiators=[7])


def test_a_round_holds_the_channel_until_its_last_pair_timeout_ends(rng):
    """The last exchange comes pair_idle_s before the round's end (the last pair's F broadcast
    still waits out its timeout): the round is done only when its time is over. A per-anchor
    round of 4 anchors (0.225 s; last exchange at 0.165 s) spans two 0.2 s steps, not one."""
    world = World(SimConfig())
    world.reset(rng)
    rnd = world.start_calibration_round(initiators=[1])
    world.step()
    assert rnd.progress == 1.0 and not rnd.done  # every exchange taken, the timeout still running
    world.step()
    assert rnd.done and world.time_s >= rnd.end_time_s
    _, steps = world.run_calibration_round()
    assert steps == int(np.ceil(world.timing.duration_s(4, 5) / 0.2 - 1e-9))
