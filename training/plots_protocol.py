"""Plots of the evaluation protocol (kept apart from evaluate.py's plots)."""

from __future__ import annotations

import sys

import numpy as np


def profile_curve(errors: np.ndarray, taus: np.ndarray) -> np.ndarray:
    """Fraction of episodes whose error is at most each of ``taus`` (a performance profile
    for a lower-is-better score, as in Agarwal et al. 2021 with the inequality reversed)."""
    return (np.asarray(errors)[:, None] <= taus[None, :]).mean(axis=0)


def _profile_batch(s: np.ndarray, taus: np.ndarray, axis: int = -1) -> np.ndarray:
    # scipy's vectorized bootstrap: resamples along ``axis``; a vector statistic leads with its own axis.
    s = np.moveaxis(s, axis, -1)
    return np.moveaxis((s[..., :, None] <= taus).mean(axis=-2), -1, 0)


def performance_profile(per_scenario: dict, path: str) -> str | None:
    """Per policy, the fraction of its episodes (all scenarios pooled) with mean tag error <= tau,
    with a 95 % band from a bootstrap over episodes."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib not installed (pip install 'uwb-env[plot]'): skipping the profile", file=sys.stderr)
        return None
    from scipy import stats

    errors: dict[str, list[float]] = {}
    for res in per_scenario.values():
        for e in res["episodes"]:
            label = e["policy"] + (" (GT)" if e["uses_ground_truth"] else "")
            errors.setdefault(label, []).append(e["mean_tag_error_m"])
    all_errors = np.concatenate([np.asarray(v) for v in errors.values()])
    taus = np.geomspace(max(all_errors.min(), 1e-3), all_errors.max(), 60)
    fig, ax = plt.subplots(figsize=(7.5, 4.5))
    for label, values in errors.items():
        x = np.asarray(values)
        curve = profile_curve(x, taus)
        line, = ax.plot(taus, curve, label=f"{label} ({len(x)} ep.)", lw=1.5)
        if len(x) > 2 and np.ptp(x) > 0:
            res = stats.bootstrap((x,), lambda s, axis=-1: _profile_batch(s, taus, axis), n_resamples=500,
                                  method="percentile", vectorized=True, random_state=np.random.default_rng(0))
            ax.fill_between(taus, res.confidence_interval.low, res.confidence_interval.high, alpha=0.15,
                            color=line.get_color())
    ax.set(xscale="log", xlabel="episode mean tag error tau (m)", ylabel="fraction of episodes with error <= tau",
           title="Performance profile over the scenario suite")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
