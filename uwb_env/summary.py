"""Plain-simulator summary used by ``uwb-env simulate``."""

from __future__ import annotations

import numpy as np

from uwb_env.config import SimConfig
from uwb_env.progress import progress
from uwb_env.sim import World


def simulate_summary(config: SimConfig, steps: int, seed: int = 0) -> dict:
    """Run ``steps`` without calibration, then one calibration round; summarize."""
    if steps < 1:
        raise ValueError(f"steps={steps!r}: must be >= 1")
    world = World(config)
    world.reset(np.random.default_rng(seed))
    lost = 0
    for _ in progress(range(steps), steps, "simulate", enabled=steps >= 20_000):
        world.step()
        lost += int(np.isnan(world.measure_tag_ranges()).sum())
    drift = world.anchor_errors_m()
    ranges, round_steps = world.run_calibration_round()
    fit = world.range_model.fit
    k = config.calibration.measurements_per_pair
    return {
        "anchors / tags / dim": f"{config.n_anchors} / {config.n_tags} / {config.dim}",
        "simulated time (s)": round(steps * config.dt_s, 3),
        "range model (fitted)": f"{fit.slope:.4f} * d + {fit.offset_m:.3f} m, std {fit.residual_std_m:.3f} m",
        "tag ranges lost (dropout / max range)": f"{lost / max(steps * config.n_anchors * config.n_tags, 1):.3%}",
        "anchor drift after run, mean (m)": round(float(drift.mean()), 3),
        "anchor drift after run, max (m)": round(float(drift.max()), 3),
        f"calibration round K={k} duration (s)": round(world.timing.duration_s(config.n_anchors, k), 3),
        "calibration round steps at dt_s": round_steps,
        "calibration pairs measured": int((ranges.count > 0).sum()),
    }
