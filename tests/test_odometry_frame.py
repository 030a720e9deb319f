"""The odometry frame's transform on hardware: fitted from motion, never guessed.

The robots report displacements in their own odometry frame; the estimates live in the first
calibration's paper frame, a rotation and possibly a reflection away. Adding displacements
unrotated (what the backend did) moves every estimate the wrong way."""

import numpy as np
import pytest

from uwb_env.config import SimConfig
from uwb_env.hardware.odometry_frame import HeldBackOdometry, OdometryFrameTracker
from uwb_env.localization.odometry_frame import fit_odometry_rotation, planar_orthogonal
from uwb_env.sim.world import World


def _draw(rng, n, motion_m):
    """Two calibrations a non-rigid motion apart: (reference, later in another frame,
    displacement in the odometry frame, the odometry frame's true transform, noise var)."""
    world0 = rng.uniform(0, 10, (n, 2))
    moved = rng.normal(0, motion_m, (n, 2))
    q = planar_orthogonal(rng.uniform(-np.pi, np.pi), bool(rng.integers(2)))  # odometry -> reference frame
    other = planar_orthogonal(rng.uniform(-np.pi, np.pi), False)  # reference frame -> the later calibration's
    sig = rng.uniform(0.02, 0.2, n)  # per-axis std of each calibration's error
    ref = world0 @ q.T + rng.normal(0, 1, (n, 2)) * sig[:, None]
    later = ((world0 + moved) @ q.T) @ other.T + rng.normal(0, 3, 2) + rng.normal(0, 1, (n, 2)) * sig[:, None]
    return ref, later, moved, q, 4 * sig**2  # var summed over axes of the difference of two


def test_fit_is_never_confidently_wrong_and_its_angle_std_is_calibrated():
    rng = np.random.default_rng(0)
    z, wrong, decided = [], 0, 0
    trials = 3000
    for _ in range(trials):
        n = int(rng.integers(3, 9))
        ref, later, moved, q, var = _draw(rng, n, rng.uniform(0.2, 2.0))
        fit = fit_odometry_rotation(ref, later, moved, var)
        if not fit.ok:
            continue
        decided += 1
        truth = np.arctan2(q[1, 0], q[0, 0])
        err = np.angle(np.exp(1j * (fit.angle_rad - truth)))
        if fit.reflected != (np.linalg.det(q) < 0) or abs(err) > 0.3:
            wrong += 1
        else:
            z.append(err / fit.angle_std_rad)
            assert np.allclose(fit.rotation, q, atol=6 * fit.angle_std_rad)
    assert wrong == 0
    assert decided > 0.6 * trials
    assert 0.9 < np.std(z) < 1.1  # the reported std is the error's
    assert abs(np.mean(z)) < 0.1


def test_a_rigid_team_motion_does_not_decide_the_frame():
    rng = np.random.default_rng(1)
    world0 = rng.uniform(0, 10, (5, 2))
    moved = np.tile([2.0, -1.0], (5, 1))  # ranges cannot see a translation of the whole team
    q = planar_orthogonal(0.7, True)
    fit = fit_odometry_rotation(world0 @ q.T, (world0 + moved) @ q.T, moved, np.full(5, 1e-3))
    assert fit.status == "unobservable" and not fit.ok


def test_a_wrong_calibration_is_a_poor_fit_not_a_frame():
    rng = np.random.default_rng(2)
    ref, later, moved, q, var = _draw(rng, 6, 1.5)
    later[2] += [1.0, 0.0]  # one anchor a metre off, with cm-level variances claimed
    fit = fit_odometry_rotation(ref, later, moved, np.full(6, 1e-3))
    assert fit.status == "poor_fit"


def test_bad_input_names_the_field():
    ref = np.zeros((4, 2))
    with pytest.raises(ValueError, match="displacement"):
        fit_odometry_rotation(ref, ref, np.zeros((3, 2)), np.ones(4))
    with pytest.raises(ValueError, match="var_m2"):
        fit_odometry_rotation(ref, ref, ref, -np.ones(4))
    with pytest.raises(ValueError, match="later"):
        fit_odometry_rotation(ref, np.full((4, 2), np.nan), ref, np.ones(4))


def test_tracker_holds_motion_back_until_the_frame_is_known_then_rotates_it():
    """The simulator's patrol motion as truth; calibrations solve it (with noise) in a frame the
    odometry does not share (rotated 120 degrees and mirrored)."""
    cfg = SimConfig.from_dict({"anchor_motion": {"model": "patrol", "patrol_radius_m": 3.0},
                               "odometry": {"model": "uniform", "uniform_error_m": 0.005}})
    world = World(cfg)
    rng = np.random.default_rng(3)
    world.reset(rng)
    to_estimate = planar_orthogonal(np.deg2rad(120.0), True)  # world -> the calibration's frame
    to_odometry = planar_orthogonal(np.deg2rad(-40.0), False)  # world -> the robots' odometry frame
    odometry = HeldBackOdometry(cfg.odometry)
    odometry.reset(cfg.n_anchors, rng)
    tracker = OdometryFrameTracker(cfg)
    tracker.reset(odometry)
    sigma = 0.03
    decided_at = None
    for step in range(1, 400):
        before = world.anchors_true.copy()
        world.step()
        moved = (world.anchors_true - before) @ to_odometry.T + rng.uniform(-0.005, 0.005, before.shape)
        applied = tracker.step(world.time_s, moved)
        odometry.note_motion(moved)
        if tracker.rotation is None:
            assert np.all(applied == 0.0)  # nothing applied in an unknown frame ...
            held = (odometry.held_back**2).sum(-1)
            assert np.all(odometry.expected_drift_var_m2(2) >= held)  # ... its length counted as error
        if step % 25 == 0:  # a calibration (an instantaneous round here)
            odometry.restart_drift()
            positions = world.anchors_true @ to_estimate.T + rng.normal(0, sigma, (cfg.n_anchors, 2))
            tracker.calibration_applied(positions, np.full(cfg.n_anchors, 2 * sigma**2), world.time_s, world.time_s)
            if tracker.rotation is not None and decided_at is None:
                decided_at = step
    assert decided_at is not None, tracker.fit
    np.testing.assert_allclose(tracker.rotation, to_estimate @ to_odometry.T, atol=0.05)
    moved = np.ones((cfg.n_anchors, 2))
    np.testing.assert_allclose(tracker.step(world.time_s, moved), moved @ tracker.rotation.T)


def test_tracker_refuses_3d_estimation():
    with pytest.raises(ValueError, match="odometry_frame='estimate' with dim=3"):
        OdometryFrameTracker(SimConfig.from_dict({"dim": 3}))


def test_a_later_calibration_mirrored_against_its_reference_carries_the_frame_flip():
    """The env may apply a calibration that comes out mirrored against the estimates (the frame
    flips); the transform into the latest frame must flip with it, not keep the old handedness."""
    from uwb_env.localization.odometry_frame import fit_odometry_rotation_chain

    rng = np.random.default_rng(5)
    n, sig = 5, 0.02
    world = [rng.uniform(0, 10, (n, 2))]
    moves = [rng.normal(0, 1.5, (n, 2)) for _ in range(3)]
    for m in moves:
        world.append(world[-1] + m)
    q = planar_orthogonal(0.9, False)  # odometry (= world here) -> the first calibration's frame
    mirrored = planar_orthogonal(-0.4, True) @ q
    frames = [q, q, mirrored, mirrored]  # the third calibration mirrored
    cal = [w @ f.T + rng.normal(0, sig, (n, 2)) for w, f in zip(world, frames, strict=True)]
    var = np.full(n, 4 * sig**2)
    fit = fit_odometry_rotation_chain([(cal[k], cal[k + 1], moves[k], var) for k in range(3)])
    assert fit.ok, fit
    np.testing.assert_allclose(fit.rotation, q, atol=0.05)
    np.testing.assert_allclose(fit.current, frames[-1], atol=0.05)  # mirrored, as the latest frame is


def _drive(tracker, odometry, world, rng, to_estimate, to_odometry_at, steps, every=25, sigma=0.03):
    """The simulator's motion as truth, calibrations every ``every`` steps (instant rounds) in the
    frame ``to_estimate``; displacements reported through ``to_odometry_at(step)``."""
    cfg = world.config
    for step in range(1, steps):
        before = world.anchors_true.copy()
        world.step()
        moved = (world.anchors_true - before) @ to_odometry_at(step).T + rng.uniform(-0.005, 0.005, before.shape)
        tracker.step(world.time_s, moved)
        odometry.note_motion(moved)
        if step % every == 0:
            odometry.restart_drift()
            positions = world.anchors_true @ to_estimate.T + rng.normal(0, sigma, (cfg.n_anchors, 2))
            tracker.calibration_applied(positions, np.full(cfg.n_anchors, 2 * sigma**2), world.time_s, world.time_s)


def _tracked(seed):
    cfg = SimConfig.from_dict({"anchor_motion": {"model": "patrol", "patrol_radius_m": 3.0},
                               "odometry": {"model": "uniform", "uniform_error_m": 0.005}})
    world = World(cfg)
    rng = np.random.default_rng(seed)
    world.reset(rng)
    odometry = HeldBackOdometry(cfg.odometry)
    odometry.reset(cfg.n_anchors, rng)
    tracker = OdometryFrameTracker(cfg)
    tracker.reset(odometry)
    return tracker, odometry, world, rng


def test_robots_with_odometry_frames_of_their_own_are_never_given_one_transform():
    """Each robot reporting in its own frame (e.g. each its own start heading): no single transform
    exists; one ok fit could pass by chance over one interval, the confirmation and the pooled
    intervals must not let it through."""
    committed = 0
    for seed in range(6):
        tracker, odometry, world, rng = _tracked(10 + seed)
        frames = np.stack([planar_orthogonal(a, False) for a in rng.uniform(-np.pi, np.pi, world.config.n_anchors)])
        cfg = world.config
        for step in range(1, 400):
            before = world.anchors_true.copy()
            world.step()
            moved = np.einsum("nij,nj->ni", frames, world.anchors_true - before)
            tracker.step(world.time_s, moved)
            odometry.note_motion(moved)
            if step % 25 == 0:
                odometry.restart_drift()
                positions = world.anchors_true + rng.normal(0, 0.03, (cfg.n_anchors, 2))
                tracker.calibration_applied(positions, np.full(cfg.n_anchors, 2 * 0.03**2), world.time_s,
                                            world.time_s)
        committed += tracker.rotation is not None
    assert committed == 0


def test_a_known_transform_that_later_calibrations_contradict_is_given_up_then_relearned():
    """The odometry frame turns by 90 degrees mid-episode (e.g. the odometry was re-initialised):
    the tracker must stop applying the old transform, then learn the new one."""
    tracker, odometry, world, rng = _tracked(3)
    to_estimate = planar_orthogonal(np.deg2rad(120.0), True)
    old, new = planar_orthogonal(np.deg2rad(-40.0), False), planar_orthogonal(np.deg2rad(50.0), False)
    _drive(tracker, odometry, world, rng, to_estimate, lambda step: old, 400)
    assert tracker.rotation is not None
    np.testing.assert_allclose(tracker.rotation, to_estimate @ old.T, atol=0.05)
    _drive(tracker, odometry, world, rng, to_estimate, lambda step: new, 1200)
    assert tracker.reverted >= 1
    assert tracker.rotation is not None
    np.testing.assert_allclose(tracker.rotation, to_estimate @ new.T, atol=0.05)


def test_a_full_pooling_window_still_commits():
    """Once the window of pooled intervals is full it slides with every calibration; the
    confirmation compares the two fits in the previous calibration's frame, so it still commits
    (it used to compare their first frames, which the slide changes, and never committed)."""
    tracker, odometry, world, rng = _tracked(3)
    tracker.max_intervals = 2
    to_estimate, to_odometry = planar_orthogonal(np.deg2rad(120.0), True), planar_orthogonal(np.deg2rad(-40.0), False)
    _drive(tracker, odometry, world, rng, to_estimate, lambda step: to_odometry, 400)
    assert tracker.rotation is not None
    np.testing.assert_allclose(tracker.rotation, to_estimate @ to_odometry.T, atol=0.05)


def test_a_calibration_without_a_covariance_is_no_evidence_and_no_crash():
    tracker, odometry, world, rng = _tracked(4)
    n = world.config.n_anchors
    tracker.calibration_applied(world.anchors_true.copy(), np.full(n, np.nan), 0.0, 0.0)  # e.g. a degenerate fit
    assert tracker.rotation is None and tracker.fit is None
    to_estimate, to_odometry = planar_orthogonal(0.3, False), planar_orthogonal(-1.0, True)
    _drive(tracker, odometry, world, rng, to_estimate, lambda step: to_odometry, 400)
    assert tracker.rotation is not None


def test_a_per_anchor_round_leaves_that_anchor_lacking_the_motion_since_its_midpoint():
    """PANS per-anchor rounds re-locate one anchor at the round's midpoint; restart_drift clears
    its held-back displacement, which must come back as the motion since the midpoint (else its
    predicted variance forgets up to a round of motion: a role-switching round lasts seconds)."""
    tracker, odometry, world, rng = _tracked(6)
    moved = np.zeros((world.config.n_anchors, 2))
    moved[1] = [0.1, 0.0]  # anchor 1 drives 0.1 m per 0.2 s step
    for k in range(1, 31):
        tracker.step(0.2 * k, moved)
    odometry.restart_drift(1)  # the system re-located anchor 1 from a round over [2.0, 4.0] s
    assert odometry.held_back[1] @ odometry.held_back[1] == 0.0
    tracker.anchor_calibration_applied(1, 2.0, 4.0)
    np.testing.assert_allclose(odometry.held_back[1], [1.5, 0.0])  # 6.0 - 3.0 s at 0.5 m/s
    assert odometry.expected_drift_var_m2(2)[1] >= 1.5**2
