"""End to end against emulated DWM1001 devices (pseudo-terminals and sockets), with faults."""

import threading
import time

import numpy as np
import pytest
from uwb_env.agents.baselines import FixedIntervalPolicy

import uwb_env
from uwb_env.config import EnvConfig
from uwb_env.env.policy import rollout
from uwb_env.hardware.backend import HardwareConfig, connect
from uwb_env.hardware.drivers import PansTlvDriver, RoundFailed, TiersAnchorDriver
from uwb_env.hardware.emulator import Faults, Scene, emulated_anchor_ids, standard_setup
from uwb_env.hardware.recording import ReplayTransport, SessionRecorder, read_session
from uwb_env.hardware.tiers import RangeMatrixMessage, TiersDecoder
from uwb_env.hardware.transport import SerialTransport
from uwb_env.localization import rigid_align

STATIC = {"anchor_motion": {"model": "static"}, "tag_motion": {"model": "static"}}


def _config(max_cycles):
    return EnvConfig.from_dict({"max_cycles": max_cycles, "sim": STATIC})


def test_episode_on_emulated_anchors_matches_ground_truth(tmp_path):
    cfg = _config(30)
    scene = Scene(cfg.sim, seed=3)
    emu, urls = standard_setup(scene)
    session = tmp_path / "session.jsonl"
    with emu:
        rec = SessionRecorder(session)
        world = connect(cfg.sim, urls["anchor"], [urls[f"tag_{i}"] for i in range(3)],
                        pans_anchor_ids=emulated_anchor_ids(), recorder=rec)
        env = uwb_env.parallel_env(config=cfg, backend=world)
        assert env.deterministic is False
        result = rollout(env, FixedIntervalPolicy(12), seed=0)
        world.close()
        rec.close()
    assert result.steps == 30
    assert env.system.calibration_count >= 3  # the first calibration + rounds at steps 12 and 24
    assert np.isnan(result.tag_error_m).all()  # no ground truth on hardware ...
    assert np.isfinite(result.reward).all() and (result.reward <= 0).all()  # ... the reward is the proxy
    est, truth = env.system.world.anchors_est, scene.anchors_true()
    rot, trans = rigid_align(est, truth)
    anchors_error = np.linalg.norm(est @ rot.T + trans - truth, axis=1)
    assert anchors_error.max() < 0.15  # cm-level ranges, 5 per pair: a few cm
    tags = env.system.tag_fix @ rot.T + trans
    assert np.linalg.norm(tags - scene.tags_true(), axis=1).max() < 0.3

    # The recording holds every byte; replaying the anchor's port through the decoder gives
    # the same number of matrices as calibrations run.
    records = read_session(session)
    assert {r["dir"] for r in records} >= {"rx", "tx"}
    replay = ReplayTransport(session, urls["anchor"], strict=True)
    replay.write(b"S")
    matrices = [m for m in TiersDecoder().feed(replay.read_available()) if isinstance(m, RangeMatrixMessage)]
    assert len(matrices) == env.system.calibration_count


def test_hung_anchor_is_reported_with_its_round_number():
    scene = Scene(_config(10).sim, seed=0)
    emu, urls = standard_setup(scene, faults={"anchor": Faults(hang=True)})
    with emu, SerialTransport(urls["anchor"]) as port:
        driver = TiersAnchorDriver(port, round_timeout_s=0.4)
        with pytest.raises(RoundFailed, match="round 1 failed: no matrix within 0.4 s"):
            driver.run_round()


def test_truncated_rows_fail_the_round_and_garbage_does_not_break_the_tags():
    cfg = _config(10)
    scene = Scene(cfg.sim, seed=0)
    faults = {"anchor": Faults(truncate_row_probability=1.0),
              "tag_0": Faults(garbage_probability=0.5, drop_char_probability=0.01)}
    emu, urls = standard_setup(scene, faults=faults)
    with emu:
        with SerialTransport(urls["anchor"]) as port:
            with pytest.raises(RoundFailed, match="round 1 failed"):
                TiersAnchorDriver(port).run_round()
        with SerialTransport(urls["tag_1"]) as port:
            tlv_driver = PansTlvDriver(port)
            loc = tlv_driver.loc_get()
            assert len(loc.distances) >= 3 and loc.node == "tag"
            tlv_driver.update_rate_set(2, 10)
            assert tlv_driver.update_rate_get() == (2, 10)
            assert tlv_driver.cfg_get()["mode"] == "tag"


def test_unplug_mid_round_then_replug_the_episode_continues(tmp_path):
    cfg = _config(40)
    scene = Scene(cfg.sim, seed=1)
    emu, urls = standard_setup(scene, transport="socket")
    session = tmp_path / "s.jsonl"
    with emu:
        rec = SessionRecorder(session)
        world = connect(cfg.sim, urls["anchor"], [urls[f"tag_{i}"] for i in range(3)],
                        pans_anchor_ids=emulated_anchor_ids(), recorder=rec,
                        hardware=HardwareConfig(round_timeout_s=1.5))
        env = uwb_env.parallel_env(config=cfg, backend=world)
        obs, infos = env.reset(seed=0)
        failed, finished, step = [], [], 0
        while env.agents:
            request = step in (2, 20)
            obs, _, _, _, infos = env.step({a: int(request) for a in env.agents})
            info = next(iter(infos.values()))
            if step == 4:  # the first round is running: pull the anchor's plug for 0.6 s
                threading.Thread(target=emu.ports["anchor"].unplug, args=(0.6,)).start()
            if info["calibration_failed"]:
                failed.append(env.calibration_error)
            if info["round_finished"] and not info["calibration_failed"]:
                finished.append(step)
            step += 1
        reconnections = world.anchor.transport.reconnections
        world.close()
        rec.close()
    assert step == 40
    assert len(failed) == 1 and "round 2 failed" in failed[0], failed  # round 1 ran in reset
    assert finished and finished[0] > 20  # the round after the replug succeeded
    assert reconnections >= 1
    events = [r["event"] for r in read_session(session) if r["dir"] == "event"]
    assert "disconnected" in events and "reconnected" in events
    assert events.index("disconnected") < events.index("reconnected")


def test_port_errors_name_the_port():
    from uwb_env.hardware.errors import PortError

    with pytest.raises(PortError, match="/dev/does-not-exist"):
        SerialTransport("/dev/does-not-exist")
    t0 = time.monotonic()
    with SerialTransport("loop://") as port:
        port.write(b"hello\n")
        assert port.read_until(b"\n", 1.0) == b"hello\n"
    assert time.monotonic() - t0 < 2


def test_scheduler_env_runs_on_emulated_devices():
    from uwb_env.env.scheduler_env import CalibrationSchedulingEnv

    cfg = _config(12)
    scene = Scene(cfg.sim, seed=4)
    emu, urls = standard_setup(scene)
    with emu:
        world = connect(cfg.sim, urls["anchor"], [urls[f"tag_{i}"] for i in range(3)],
                        pans_anchor_ids=emulated_anchor_ids())
        env = CalibrationSchedulingEnv(cfg, backend=world)
        obs, info = env.reset(seed=0)
        assert env.observation_space.contains(obs)
        for t in range(12):
            obs, reward, terminated, truncated, info = env.step(int(t == 2))
            assert env.observation_space.contains(obs) and np.isfinite(reward)
        world.close()
    assert truncated and not terminated
    assert info["calibration_count"] == 2 and info["ground_truth"] is False


def test_scene_range_noise_does_not_depend_on_how_far_wall_time_moved_the_world():
    # a stalled test thread lets the wall-clock world take more steps before a measurement:
    # that may move the robots, but must not change the noise the next ranges draw
    cfg = EnvConfig.from_dict({})
    fresh, stalled = Scene(cfg.sim, seed=7, speedup=0.0), Scene(cfg.sim, seed=7, speedup=0.0)
    for _ in range(25):
        stalled.world.step()
    a, b = np.zeros(2), np.array([3.0, 4.0])
    np.testing.assert_array_equal(fresh.measure(a, b, 10), stalled.measure(a, b, 10))
    assert not np.array_equal(fresh.world.anchors_true, stalled.world.anchors_true)  # it did move


def test_moving_team_with_odometry_in_its_own_frame():
    """The robots' odometry reports in a frame rotated and mirrored against the calibration's
    paper frame (as real odometry does: nothing aligns the two). Displacements are held back
    until the transform is fitted from the motion, then rotated; the backend used to add them
    as they came, moving every estimate the wrong way."""
    cfg = EnvConfig.from_dict({"max_cycles": 90, "sim": {
        "tag_motion": {"model": "static"}, "anchor_motion": {"model": "patrol", "patrol_radius_m": 3.0},
        "odometry": {"model": "uniform", "uniform_error_m": 0.005}}})
    scene = Scene(cfg.sim, seed=3)
    emu, urls = standard_setup(scene)
    c, s = np.cos(2.1), np.sin(2.1)
    to_odometry = np.array([[c, -s], [s, c]]) @ np.diag([1.0, -1.0])  # world -> the robots' odometry frame
    rng = np.random.default_rng(0)
    last = [scene.anchors_true()]

    def odometry(dt_s):
        now = scene.anchors_true()
        moved, last[0] = now - last[0], now
        return (moved + rng.uniform(-0.005, 0.005, moved.shape)) @ to_odometry.T

    with emu:
        world = connect(cfg.sim, urls["anchor"], [urls[f"tag_{i}"] for i in range(3)],
                        pans_anchor_ids=emulated_anchor_ids(), odometry_source=odometry)
        env = uwb_env.parallel_env(config=cfg, backend=world)
        env.reset(seed=0)
        frame = world.odometry_frame
        held_back_seen = False
        for step in range(90):
            env.step({a: int(step % 10 == 9) for a in env.agents})
            if frame.rotation is None and np.abs(world.odometry.held_back).max() > 0.05:
                held_back_seen = True  # the estimates did not move; the predicted error says so
                held = (world.odometry.held_back**2).sum(-1)
                assert np.all(env.system.predicted_anchor_var_m2() >= held)
        est, truth = world.anchors_est.copy(), scene.anchors_true()
        world.close()
    assert held_back_seen
    assert frame.rotation is not None, frame.fit  # decided from the motion ...
    rot, trans = rigid_align(truth, est)  # world -> the estimate frame
    np.testing.assert_allclose(frame.rotation, rot @ to_odometry.T, atol=0.1)  # ... and right
    assert np.linalg.norm(truth @ rot.T + trans - est, axis=1).max() < 0.2
