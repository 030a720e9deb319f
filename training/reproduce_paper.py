"""Reproduce the paper's simulation (Sec. 4, Figs. 4 and 5) from its text alone.

``python -m uwb_env.training.reproduce_paper [--runs 40 --steps 300] [--out DIR]`` writes into
``--out`` (default ``runs/reproduce_paper``; ``--out docs/results`` refreshes the committed copy):
``paper_reproduction.json`` and ``.md`` (every reading's medians and quartiles beside the paper's,
and which reading matches which of the paper's numbers), ``paper_fig4.png``
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

The paper does not say exactly how its errors are measured, so three readings of the same
runs are reported side by side:

- ``anchor0``: as the paper defines its frame: positions relative to anchor 0 (the origin), in
  the frame of the first calibration (the figures' reading);
- ``aligned``: after the rigid alignment of the true anchors onto their estimates (the env's
  own metric: a range-only calibration cannot observe the drift of the whole frame);
- ``true_anchors``: tags fixed from the *true* anchor positions (an independent range draw of
  the same model, from a generator of its own: the simulation's stream is untouched), which
  isolates the tag solver from anchor error.

The rotation error is the signed angle between the estimated and true direction anchor 0 ->
anchor 1 (the x axis).
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
READINGS = {"anchor0": "relative to anchor 0 (paper frame)", "aligned": "aligned to the estimated anchors",
            "true_anchors": "tags from the true anchors"}
MATCH_TOLERANCE = 0.25  # a reading "matches" a paper median within +-25 %


@dataclass
class Args:
    runs: int = 40
    steps: int = 300
    workers: int = 2
    out: str = "runs/reproduce_paper"
    quick: bool = False


def run(seed: int, steps: int) -> dict[str, np.ndarray]:
    """One run; per step and reading (see the module docstring): anchor errors, tag errors; and
    the signed x-axis rotation error. The ``anchor0`` arrays keep their historical names."""
    from uwb_env.agents.baselines import FixedIntervalPolicy

    from uwb_env.config import EnvConfig
    from uwb_env.env.parallel_env import UWBCalibrationParallelEnv

    config = EnvConfig.from_dict({**PAPER_SETUP, "max_cycles": steps})
    env = UWBCalibrationParallelEnv(config)
    policy = FixedIntervalPolicy(CALIBRATION_INTERVAL_STEPS)
    policy.reset(seed)
    obs, infos = env.reset(seed=seed)
    own = np.random.default_rng([seed, 0x7A65])  # the true-anchor reading's range draws
    anchors, tags, rotation, aligned_a, aligned_t, true_t = [], [], [], [], [], []
    while env.agents:
        obs, _, _, _, infos = env.step(policy.act(obs, infos))
        a, t, r = paper_frame_errors(env.system)
        anchors.append(a)
        tags.append(t)
        rotation.append(r)
        aligned_a.append(env.system.anchor_errors_m())
        aligned_t.append(env.system.tag_errors_m())
        true_t.append(tags_from_true_anchors(env.system, own))
    return {"anchor_error_m": np.array(anchors), "tag_error_m": np.array(tags),
            "rotation_error_rad": np.array(rotation), "aligned_anchor_error_m": np.array(aligned_a),
            "aligned_tag_error_m": np.array(aligned_t), "true_anchors_tag_error_m": np.array(true_t)}


def tags_from_true_anchors(system, rng: np.random.Generator) -> np.ndarray:
    """Each tag's error when fixed (least squares, as the paper) from the true anchor positions."""
    from uwb_env.localization import locate_tags

    world = system.world
    truth_a = world.to_estimate_frame(world.anchors_true)
    truth_t = world.to_estimate_frame(world.tags_true)
    raw = system.range_model.measure(np.linalg.norm(truth_a[:, None] - truth_t[None], axis=-1), rng).T
    ranges = np.maximum(world.tag_correction.correct(raw), 0.0)
    fix = locate_tags(truth_a, ranges, system.range_std_m, loss="linear", with_covariance=False)
    return np.linalg.norm(fix.positions - truth_t, axis=1)


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
    pooled = {"anchor0": (anchors, tags),
              "aligned": tuple(np.concatenate([r[f"aligned_{k}_error_m"].ravel() for r in results])
                               for k in ("anchor", "tag")),
              "true_anchors": (None, np.concatenate([r["true_anchors_tag_error_m"].ravel() for r in results]))}
    readings = {name: {"description": READINGS[name],
                       **({"anchor": box_stats(a)} if a is not None else {}), "tag": box_stats(t)}
                for name, (a, t) in pooled.items()}
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
        **{f"{kind}_error_median_m_{name}": r[kind]["median"] for name, r in readings.items()
           for kind in ("anchor", "tag") if kind in r},
        "readings": readings,
        "matches": match_readings(readings, theirs),
        "setup": PAPER_SETUP | {"calibration_interval_steps": CALIBRATION_INTERVAL_STEPS},
    }
    print(format_table(summary))
    print(format_readings(summary))
    os.makedirs(args.out, exist_ok=True)
    suffix = "_quick" if args.quick else ""
    json_path = os.path.join(args.out, f"paper_reproduction{suffix}.json")
    with open(json_path, "w") as f:
        json.dump(summary, f, indent=1)
    md_path = os.path.join(args.out, f"paper_reproduction{suffix}.md")
    with open(md_path, "w") as f:
        f.write(format_markdown(summary))
    plot(results[0], anchors, tags, rotation, paper, args.out, suffix)
    print(f"wrote {json_path}, {md_path}, paper_fig4{suffix}.png and paper_fig5{suffix}.png in {args.out}/")
    return summary


def match_readings(readings: dict, theirs: dict) -> dict[str, dict]:
    """For each of the paper's medians (anchor, tag): every reading's ratio ours / paper, the
    closest reading, and whether it is within ``MATCH_TOLERANCE``."""
    out = {}
    for kind in ("anchor", "tag"):
        paper = theirs[kind]["median"]
        ratios = {name: r[kind]["median"] / paper for name, r in readings.items() if kind in r}
        closest = min(ratios, key=lambda n: abs(np.log(ratios[n])))
        out[kind] = {"paper_median_m": paper, "ratio_by_reading": ratios, "closest_reading": closest,
                     "matches": bool(abs(ratios[closest] - 1) <= MATCH_TOLERANCE)}
    return out


def format_readings(s: dict) -> str:
    lines = [f"{'reading':52s} {'anchor median (m)':>18s} {'tag median (m)':>15s}"]
    for name, r in s["readings"].items():
        a = f"{r['anchor']['median']:.3f}" if "anchor" in r else "-"
        lines.append(f"{r['description'] + ' [' + name + ']':52s} {a:>18s} {r['tag']['median']:>15.3f}")
    lines.append(f"{'paper (Fig. 5)':52s} {s['paper_anchor_error_median_m']:>18.3f} "
                 f"{s['paper_tag_error_median_m']:>15.3f}")
    for kind, m in s["matches"].items():
        verdict = "matches" if m["matches"] else "is closest to, but does not match,"
        lines.append(f"the paper's {kind} median {m['paper_median_m']:.3f} m: reading '{m['closest_reading']}' "
                     f"{verdict} it (ratio {m['ratio_by_reading'][m['closest_reading']]:.2f}, tolerance "
                     f"+-{MATCH_TOLERANCE:.0%})")
    same = {m["closest_reading"] for m in s["matches"].values()}
    lines.append("one reading reproduces both of the paper's medians" if len(same) == 1 and
                 all(m["matches"] for m in s["matches"].values()) else
                 "no single reading reproduces both of the paper's medians")
    return "\n".join(lines)


def format_markdown(s: dict) -> str:
    head = (f"# Paper reproduction ({s['runs']} runs x {s['steps_per_run']} steps, {s['date']}"
            f"{', quick' if s['quick'] else ''})\n\n"
            "Generated by `python -m uwb_env.training.reproduce_paper`. Medians over every step, anchor and tag of "
            "every run; the paper's from its Fig. 5 box plots.\n\n")
    table = ["| reading | anchor median (m) | tag median (m) |", "| --- | ---: | ---: |"]
    for name, r in s["readings"].items():
        a = f"{r['anchor']['median']:.3f}" if "anchor" in r else "-"
        table.append(f"| {r['description']} (`{name}`) | {a} | {r['tag']['median']:.3f} |")
    table.append(f"| paper, Fig. 5 | {s['paper_anchor_error_median_m']:.3f} | {s['paper_tag_error_median_m']:.3f} |")
    verdicts = format_readings(s).splitlines()[len(s["readings"]) + 2:]
    return head + "\n".join(table) + "\n\n" + "\n".join(f"- {v}" for v in verdicts) + "\n\n```\n" + \
        format_table(s) + "\n```\n"


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
    p.add_argument("--out", default=d.out, help=f"output folder (default {d.out}; docs/results refreshes the "
                   "committed copy)")
    p.add_argument("--quick", action="store_true", help="6 runs of 120 steps (files get a _quick suffix)")
    main(Args(**vars(p.parse_args())))
