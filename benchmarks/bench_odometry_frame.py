"""The odometry frame on hardware: is the fitted transform right, and what does it buy?

Synthetic (``fit_odometry_rotation`` alone): two calibrations of N = 3-8 anchors a random
non-rigid motion of 0.2-2 m apart, per-anchor errors 2-20 cm, the odometry frame a random
rotation (half of them mirrored) away. Figures: the fraction decided ``ok``, how many of those
have the wrong handedness (a mirrored frame: must be 0) or an angle more than 0.3 rad off
(beyond 3.4 std at the largest std an ``ok`` allows: a Gaussian tail or a wrong basin), and
the angle errors of the right-handed ones in units of their reported std (std 1 = calibrated).
Then the same with the real errors 1.5x the stds the fit is told (a misspecified noise model).

The full system (``LocalizationSystem`` on the simulator driven as the hardware backend drives
its estimates: rounds while the robots move, the distance odometry model's errors, no ground
truth for the system; 100 episodes of 300 steps, a team round every 15): a shared odometry
frame (random, half mirrored) in the default scenario and with anchors patrolling 3 m, and the
misconfiguration of robots that each report in their own frame; and the default scenario with
the displacements added as they come (the behaviour before). Figures: episodes that
committed a transform, commits (a transform dropped and learnt again counts twice), wrong ones
(mirrored or more than 0.3 rad off for the estimate frame of the moment; in the own-frames case
every commit is wrong for most robots), the step of the first, the anchors' mean error over
the last 50 steps after a rigid alignment to the truth (median over episodes).

Emulated (the full env on the TIERS emulator over pseudo-terminals, ``fixed:10``, 90 steps of
0.2 s, anchors patrolling 3 m around their slots, odometry reported in a frame rotated by 120
degrees and mirrored against the world, 5 mm of odometry noise): the estimate frame's
transform fitted from the motion (``odometry_frame="estimate"``, this tree) beside the earlier
behaviour of adding displacements as they come (``odometry_frame="calibration"``), alternating
per seed. Figures: episodes that decided the transform, calibrations it took, the fitted
transform's error against the truth, and the anchors' mean error (after a rigid alignment to
the truth) over each episode's last 30 steps.

    python benchmarks/bench_odometry_frame.py [--quick]

Writes benchmarks/results/bench_odometry_frame.json (``_quick`` with --quick).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._common import print_table, write_results  # noqa: E402
from uwb_env.localization.odometry_frame import fit_odometry_rotation, planar_orthogonal  # noqa: E402


def synthetic(trials: int, noise_scale: float, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    decided = mirrored = off_angle = 0
    z = []
    for _ in range(trials):
        n = int(rng.integers(3, 9))
        world0 = rng.uniform(0, 10, (n, 2))
        moved = rng.normal(0, rng.uniform(0.2, 2.0), (n, 2))
        q = planar_orthogonal(rng.uniform(-np.pi, np.pi), bool(rng.integers(2)))
        other = planar_orthogonal(rng.uniform(-np.pi, np.pi), False)
        sig = rng.uniform(0.02, 0.2, n)
        real = noise_scale * sig[:, None]
        ref = world0 @ q.T + rng.normal(0, 1, (n, 2)) * real
        later = ((world0 + moved) @ q.T) @ other.T + rng.normal(0, 3, 2) + rng.normal(0, 1, (n, 2)) * real
        fit = fit_odometry_rotation(ref, later, moved, 4 * sig**2)
        if not fit.ok:
            continue
        decided += 1
        err = float(np.angle(np.exp(1j * (fit.angle_rad - np.arctan2(q[1, 0], q[0, 0])))))
        if fit.reflected != (np.linalg.det(q) < 0):
            mirrored += 1
            continue
        off_angle += abs(err) > 0.3
        z.append(err / fit.angle_std_rad)
    return {"trials": trials, "ok_rate": decided / trials, "ok_mirrored": mirrored, "ok_angle_over_0p3rad": off_angle,
            "angle_z_std": float(np.std(z)) if z else float("nan")}


def _system_episode(seed: int, to_odometry: np.ndarray, sim: dict, steps: int, every: int,
                    mode: str = "estimate") -> dict:
    """One episode of the full LocalizationSystem on the simulator driven as the hardware backend
    drives its estimates: no ground truth for the system, each robot's displacements (with the
    odometry model's errors) reported through ``to_odometry`` (n, 2, 2: world -> its odometry
    frame) and passed through :class:`OdometryFrameTracker`; rounds run while the robots move."""
    from uwb_env.config import EnvConfig
    from uwb_env.hardware.odometry_frame import HeldBackOdometry, OdometryFrameTracker
    from uwb_env.localization import rigid_align
    from uwb_env.sim.world import World
    from uwb_env.system import LocalizationSystem

    class World2(World):
        has_ground_truth = False

        def reset(self, rng):
            super().reset(rng)
            self.errors = self.odometry  # draws the odometry's errors, in the world frame
            self.odometry = HeldBackOdometry(self.config.odometry)
            self.odometry.reset(self.config.n_anchors, np.random.default_rng(1), 2)
            self.tracker = OdometryFrameTracker(self.config, mode)
            self.tracker.reset(self.odometry)
            self.anchors_est = np.zeros((self.config.n_anchors, 2))
            self.log = []

        def step(self):
            n = self._n
            before = self.motion.positions[:n].copy() if self.round is not None else None
            delta, turn = self.motion.step(self.dt_s, self.rng)
            moved = np.einsum("nij,nj->ni", to_odometry,
                              self.errors.estimated_displacement(delta[:n], turn[:n], self.dt_s, self.rng))
            t0 = self.time_s
            self.step_count += 1
            self.time_s = self.step_count * self.dt_s
            self.anchors_est += self.tracker.step(self.time_s, moved)
            self.odometry.note_motion(moved)
            if self.round is not None:
                self.round.advance(t0, self.time_s, before, self.motion.positions[:n], self.range_model, self.rng)

        def calibration_applied(self, positions, var_m2, start_s, end_s):
            had = self.tracker.rotation is not None
            self.anchors_est += self.tracker.calibration_applied(positions, var_m2, start_s, end_s)
            if not had and self.tracker.rotation is not None:
                truth_to_est, _ = rigid_align(self.anchors_true, self.anchors_est)
                self.log.append(truth_to_est)

        def set_estimate_frame(self, rotation, origin):
            self.frame_rotation, self.frame_origin = rotation, origin

    cfg = EnvConfig.from_dict({"sim": sim})
    world = World2(cfg.sim)
    system = LocalizationSystem(cfg, world=world)
    system.reset(np.random.default_rng(seed))
    n = cfg.sim.n_anchors
    commits, wrong, errors = [], 0, []
    for k in range(steps):
        system.step(np.full(n, k % every == every - 1))
        if world.log and mode == "estimate":  # a transform just committed: world -> estimate composed right?
            truth_to_est = world.log.pop()
            expected = truth_to_est @ np.linalg.inv(to_odometry[0])
            m = world.tracker.rotation @ expected.T
            commits.append(k)
            wrong += bool(np.linalg.det(m) < 0 or abs(np.arctan2(m[1, 0], m[0, 0])) > 0.3)
        rot, trans = rigid_align(world.anchors_true, world.anchors_est)
        errors.append(float(np.linalg.norm(world.anchors_true @ rot.T + trans - world.anchors_est, axis=1).mean()))
    return {"commits": len(commits), "wrong": wrong, "first_commit_step": commits[0] if commits else None,
            "error_last50_m": float(np.mean(errors[-50:]))}


def system_scenarios(episodes: int) -> dict:
    """The full LocalizationSystem on the simulator standing in for the hardware (300 steps, a
    team round every 15 steps, the distance odometry model): a shared odometry frame (random,
    half mirrored) in the default scenario and with anchors patrolling 3 m, and the
    misconfiguration of robots that each report in their own random frame."""
    out = {}
    base = {"odometry": {"model": "distance"}}
    patrol3 = dict(base, anchor_motion={"model": "patrol", "patrol_radius_m": 3.0})
    cases = (("shared_default", base, False, "estimate"), ("shared_default_as_they_come", base, False, "calibration"),
             ("shared_patrol3", patrol3, False, "estimate"), ("own_frames_patrol3", patrol3, True, "estimate"))
    for name, sim, own, mode in cases:
        rows = []
        for e in range(episodes):
            rng = np.random.default_rng(1000 + e)
            shared = planar_orthogonal(rng.uniform(-np.pi, np.pi), bool(rng.integers(2)))
            frames = np.stack([planar_orthogonal(rng.uniform(-np.pi, np.pi), False) @ shared if own else shared
                               for _ in range(4)])
            rows.append(_system_episode(1000 + e, frames, sim, steps=300, every=15, mode=mode))
        decided = [r for r in rows if r["commits"]]
        out[name] = {"episodes": episodes, "decided_episodes": len(decided),
                     "commits": sum(r["commits"] for r in rows), "wrong_commits": sum(r["wrong"] for r in rows),
                     "first_commit_step_median": float(np.median([r["first_commit_step"] for r in decided]))
                     if decided else float("nan"),
                     "error_last50_m_median": float(np.median([r["error_last50_m"] for r in rows]))}
    return out


def emulated_episode(mode: str, seed: int, steps: int = 90) -> dict:
    import uwb_env
    from uwb_env.config import EnvConfig
    from uwb_env.hardware.backend import HardwareConfig, connect
    from uwb_env.hardware.emulator import Scene, emulated_anchor_ids, standard_setup
    from uwb_env.localization import rigid_align

    cfg = EnvConfig.from_dict({"max_cycles": steps, "sim": {
        "tag_motion": {"model": "static"}, "anchor_motion": {"model": "patrol", "patrol_radius_m": 3.0},
        "odometry": {"model": "uniform", "uniform_error_m": 0.005}}})
    scene = Scene(cfg.sim, seed=seed)
    emu, urls = standard_setup(scene)
    to_odometry = planar_orthogonal(np.deg2rad(120.0), True)  # world -> the robots' odometry frame
    rng = np.random.default_rng(seed)
    last = [scene.anchors_true()]

    def odometry(dt_s):
        now = scene.anchors_true()
        moved, last[0] = now - last[0], now
        return (moved + rng.uniform(-0.005, 0.005, moved.shape)) @ to_odometry.T

    errors, decided_at = [], None
    with emu:
        world = connect(cfg.sim, urls["anchor"], [urls[f"tag_{i}"] for i in range(3)],
                        pans_anchor_ids=emulated_anchor_ids(), odometry_source=odometry,
                        hardware=HardwareConfig(odometry_frame=mode))
        env = uwb_env.parallel_env(config=cfg, backend=world)
        env.reset(seed=seed)
        frame = world.odometry_frame
        for step in range(steps):
            env.step({a: int(step % 10 == 9) for a in env.agents})
            est, truth = world.anchors_est.copy(), scene.anchors_true()
            rot, trans = rigid_align(truth, est)
            errors.append(float(np.linalg.norm(truth @ rot.T + trans - est, axis=1).mean()))
            if mode == "estimate" and frame.rotation is not None and decided_at is None:
                decided_at = env.system.calibration_count
        rotation_error = float(np.abs(frame.rotation - rot @ to_odometry.T).max()) if frame.rotation is not None \
            else float("nan")
        world.close()
    return {"decided_at": decided_at, "rotation_error": rotation_error,
            "error_last30_m": float(np.mean(errors[-30:]))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args()
    t0 = time.perf_counter()
    trials = 2000 if args.quick else 20000
    right = synthetic(trials, 1.0, seed=0)
    off = synthetic(trials, 1.5, seed=1)
    print_table("Synthetic fits (0 mirrored ok wanted; angle z std 1 = calibrated)",
                ["noise model", "trials", "ok rate", "ok mirrored", "ok > 0.3 rad off", "angle z std"],
                [[name, trials, r["ok_rate"], r["ok_mirrored"], r["ok_angle_over_0p3rad"], r["angle_z_std"]]
                 for name, r in (("as told", right), ("1.5x worse", off))])
    system = system_scenarios(5 if args.quick else 100)
    print_table("The full system on the simulator as hardware (300 steps, a round every 15)",
                ["case", "episodes", "decided", "commits", "wrong commits", "first commit step", "error m (last 50)"],
                [[k, v["episodes"], v["decided_episodes"], v["commits"], v["wrong_commits"],
                  v["first_commit_step_median"], v["error_last50_m_median"]] for k, v in system.items()])
    seeds = [3] if args.quick else [3, 5, 7, 11, 13]
    rows, fitted, old = [], [], []
    for seed in seeds:
        new = emulated_episode("estimate", seed)
        before = emulated_episode("calibration", seed)
        fitted.append(new)
        old.append(before)
        rows.append([seed, str(new["decided_at"]), new["rotation_error"], new["error_last30_m"],
                     before["error_last30_m"], before["error_last30_m"] / new["error_last30_m"]])
    print_table("Emulated episodes (odometry frame rotated 120 deg and mirrored)",
                ["seed", "decided at calibration", "rotation error", "anchor error m (fitted)",
                 "anchor error m (as they come)", "ratio"], rows)
    decided = [f["decided_at"] for f in fitted if f["decided_at"] is not None]
    new_err = float(np.mean([f["error_last30_m"] for f in fitted]))
    old_err = float(np.mean([f["error_last30_m"] for f in old]))
    figures = {
        "synthetic_trials": trials,
        "synthetic_ok_rate": right["ok_rate"],
        "synthetic_ok_mirrored": right["ok_mirrored"],
        "synthetic_ok_angle_over_0p3rad": right["ok_angle_over_0p3rad"],
        "synthetic_angle_z_std": right["angle_z_std"],
        "synthetic_misspecified_1p5x_ok_rate": off["ok_rate"],
        "synthetic_misspecified_1p5x_ok_mirrored": off["ok_mirrored"],
        "synthetic_misspecified_1p5x_ok_angle_over_0p3rad": off["ok_angle_over_0p3rad"],
        "emulated_episodes": len(seeds),
        "emulated_decided_episodes": len(decided),
        "emulated_calibrations_to_decide_median": float(np.median(decided)) if decided else float("nan"),
        "emulated_rotation_error_max": float(np.nanmax([f["rotation_error"] for f in fitted])),
        "emulated_anchor_error_last30_m_fitted": new_err,
        "emulated_anchor_error_last30_m_as_they_come": old_err,
        "emulated_as_they_come_over_fitted": old_err / new_err,
        **{f"system_{case}_{key}": value for case, v in system.items() for key, value in v.items()},
        "bench_seconds": time.perf_counter() - t0,
    }
    write_results("bench_odometry_frame_quick" if args.quick else "bench_odometry_frame", figures, args.quick)


if __name__ == "__main__":
    main()
