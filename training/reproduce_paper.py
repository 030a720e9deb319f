"""Reproduce the paper's simulation (Sec. 4, Figs. 4 and 5) from its text alone.

``python -m uwb_env.training.reproduce_paper [--runs 40 --steps 300]`` writes into ``docs/results/``:
``paper_reproduction.json`` (medians and quartiles beside the paper's), ``paper_fig4.png``
(anchor and tag errors over 55 steps, ours beside the paper's series) and ``paper_fig5.png``
(box plots of translation and x-axis rotation error from many runs of hundreds of steps).

What the paper fixes, and we use: 4 anchors, 3 tags inside the anchors' polygon, motion in a
constant direction with Gaussian noise, every step a uniform (-0.1 m, +0.1 m) error added to
each anchor's on-board estimate, calibration every 10 steps, least squares (no robust loss)
for calibration and tags, the DWM1001 range model fitted to the measured data (LOS: no NLOS,
no dropouts), K = 5 measurements per pair, the paper's frame rules.

What it leaves open, chosen once here (not tuned to match the paper's plots):

- ``dt_s = 1.0``: one simulation step per second, so a 4-anchor round (0.9 s at K = 5) fits
  inside the step that calls it, as calibrations are instantaneous events in the paper.
- speeds 0.1-0.3 m/s: slow ground robots, moving about as far per step as the odometry error.
- a 10 m x 10 m area: between the paper's 9 m^2 and 144 m^2 experiments.

Errors are measured as the paper defines its frame: positions relative to anchor 0 (the
origin), in the frame of the first calibration; the rotation error is the signed angle
between the estimated and true direction anchor 0 -> anchor 1 (the x axis).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import platform
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from datetime import date

import numpy as np

PAPER_SETUP = {
    "max_cycles": 300,
    "tag_error_weight": 1.0,
    "solver": {"loss": "linear", "gauge": "anchor0", "use_anchor_covariance": False},
    "sim": {
        "n_anchors": 4, "n_tags": 3, "dim": 2, "dt_s": 1.0, "area_size_m": 10.0,
        "anchor_motion": {"model": "heading", "speed_min_mps": 0.1, "speed_max_mps": 0.3},
        "tag_motion": {"model": "heading", "speed_min_mps": 0.1, "speed_max_mps": 0.3},
        "odometry": {"model": "uniform", "uniform_error_m": 0.1},
        "ranging": {"nlos_probability": 0.0, "dropout_probability": 0.0},
        "calibration": {"measurements_per_pair": 5},
    },
}
CALIBRATION_INTERVAL_STEPS = 10
SEED_BASE = 2_000_000  # apart from uwb_env.training and evaluation seeds


@dataclass
class Args:
    runs: int = 40
    steps: int = 300
    workers: int = 2
    out: str = "docs/results"
    quick: bool = False


def run(seed: int, steps: int) -> dict[str, np.ndarray]:
    """One run; per step: anchors 1..N-1 error, tag errors, signed x-axis rotation error."""
    from uwb_env.agents.baselines import FixedIntervalPolicy

    from uwb_env.config import EnvConfig
    from uwb_env.env.parallel_env import UWBCalibrationParallelEnv

    config = EnvConfig.from_dict({**PAPER_SETUP, "max_cycles": steps})
    env = UWBCalibrationParallelEnv(config)
    policy = FixedIntervalPolicy(CALIBRATION_INTERVAL_STEPS)
    policy.reset(seed)
    obs, infos = env.reset(seed=seed)
    anchors, tags, rotation = [], [], []
    while env.agents:
        obs, _, _, _, infos = env.step(policy.act(obs, infos))
        a, t, r = paper_frame_errors(env.system)
        anchors.append(a)
        tags.append(t)
        rotation.append(r)
    return {"anchor_error_m": np.array(anchors), "tag_error_m": np.array(tags),
            "rotation_error_rad": np.array(rotation)}


def paper_frame_errors(system) -> tuple[np.ndarray, np.ndarray, float]:
    world = system.world
    truth_a = world.to_estimate_frame(world.anchors_true)
    truth_t = world.to_estimate_frame(world.tags_true)
    est_a = world.anchors_est
    # The paper's frame: anchor 0 is the origin (of the truth and of the estimates alike).
    anchor = np.linalg.norm((est_a[1:] - est_a[0]) - (truth_a[1:] - truth_a[0]), axis=1)
    tag = np.linalg.norm((system.tag_fix - est_a[0]) - (truth_t - truth_a[0]), axis=1)
    u, v = est_a[1] - est_a[0], truth_a[1] - truth_a[0]
    rotation = float(np.arctan2(u[0] * v[1] - u[1] * v[0], u @ v))
    return anchor, tag, rotation


def _run_star(job):
    return run(*job)


def box_stats(values: np.ndarray) -> dict[str, float]:
    q1, med, q3 = np.percentile(values, [25, 50, 75])
    iqr = q3 - q1
    inside = values[(values >= q1 - 1.5 * iqr) & (values <= q3 + 1.5 * iqr)]
    return {"q1": float(q1), "median": float(med), "q3": float(q3), "whisker_low": float(inside.min()),
            "whisker_high": float(inside.max())}


def main(args: Args) -> dict:
    from uwb_env.training.paper_data import load_reference

    from uwb_env.progress import progress

    runs, steps = (6, 120) if args.quick else (args.runs, args.steps)
    jobs = [(SEED_BASE + i, steps) for i in range(runs)]
    with ProcessPoolExecutor(max_workers=args.workers, mp_context=multiprocessing.get_context("forkserver")) as pool:
        results = list(progress(pool.map(_run_star, jobs), runs, "reproduce_paper"))
    anchors = np.concatenate([r["anchor_error_m"].ravel() for r in results])
    tags = np.concatenate([r["tag_error_m"].ravel() for r in results])
    rotation = np.concatenate([r["rotation_error_rad"] for r in results])
    paper = load_reference()
    ours = {"anchor": box_stats(anchors), "tag": box_stats(tags), "rotation": box_stats(rotation)}
    theirs = {"anchor": paper["fig5_anchor_translation_error_m"], "tag": paper["fig5_tag_translation_error_m"],
              "rotation": paper["fig5_x_axis_rotation_error_rad"]}
    summary = {
        "date": date.today().isoformat(), "machine": platform.machine() + " " + platform.node(),
        "runs": runs, "steps_per_run": steps, "quick": args.quick,
        "anchor_error_median_m": ours["anchor"]["median"],
        "tag_error_median_m": ours["tag"]["median"],
        "rotation_error_median_rad": ours["rotation"]["median"],
        "abs_rotation_error_median_rad": float(np.median(np.abs(rotation))),
        "paper_anchor_error_median_m": theirs["anchor"]["median"],
        "paper_tag_error_median_m": theirs["tag"]["median"],
        "paper_rotation_error_median_rad": theirs["rotation"]["median"],
        **{f"{k}_{s}": v for k, st in ours.items() for s, v in st.items() if s != "median"},
        **{f"paper_{k}_{s}": theirs[k][s] for k in theirs for s in ("q1", "q3", "whisker_low", "whisker_high")},
        "setup": PAPER_SETUP | {"calibration_interval_steps": CALIBRATION_INTERVAL_STEPS},
    }
    print(format_table(summary))
    os.makedirs(args.out, exist_ok=True)
    suffix = "_quick" if args.quick else ""
    with open(os.path.join(args.out, f"paper_reproduction{suffix}.json"), "w") as f:
        json.dump(summary, f, indent=1)
    plot(results[0], anchors, tags, rotation, paper, args.out, suffix)
    return summary


def format_table(s: dict) -> str:
    lines = [f"{'quantity':32s} {'ours q1/med/q3':>26s} {'paper q1/med/q3':>26s}"]
    for key, label, unit in (("anchor", "anchor translation error", "m"), ("tag", "tag translation error", "m"),
                             ("rotation", "x-axis rotation error", "rad")):
        med_key = {"anchor": "anchor_error_median_m", "tag": "tag_error_median_m",
                   "rotation": "rotation_error_median_rad"}[key]
        ours = f"{s[f'{key}_q1']:.4f}/{s[med_key]:.4f}/{s[f'{key}_q3']:.4f}"
        paper = f"{s[f'paper_{key}_q1']:.4f}/{s['paper_' + med_key]:.4f}/{s[f'paper_{key}_q3']:.4f}"
        lines.append(f"{label + ' (' + unit + ')':32s} {ours:>26s} {paper:>26s}")
    return "\n".join(lines)


def plot(first: dict, anchors, tags, rotation, paper: dict, out: str, suffix: str) -> list[str]:
    """Fig. 4 and Fig. 5 (training/plots.py); skipped with a note when matplotlib is missing."""
    from uwb_env.training.plots import paper_figures

    return paper_figures(first, anchors, tags, rotation, paper, out, suffix)


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    d = Args()
    p.add_argument("--runs", type=int, default=d.runs)
    p.add_argument("--steps", type=int, default=d.steps)
    p.add_argument("--workers", type=int, default=d.workers)
    p.add_argument("--out", default=d.out)
    p.add_argument("--quick", action="store_true", help="6 runs of 120 steps (files get a _quick suffix)")
    main(Args(**vars(p.parse_args())))
