"""Figures of ``uwb-env evaluate`` and of the paper reproduction (the ``plot`` extra).

Every entry point returns the paths it wrote, or ``[]`` with one note on stderr when matplotlib
is not installed: the numbers are already on disk and plots are optional.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np

SMOOTH_S = 5.0  # rolling-median window of the error-over-time curves


def _pyplot():
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib not installed (pip install 'uwb-env[plot]'): skipping plots", file=sys.stderr)
        return None
    return plt


def short_label(spec: str) -> str:
    """A policy spec for a legend: model paths reduced to the model's folder name, never absolute."""
    name, sep, param = spec.partition(":")
    if not sep or ("/" not in param and "\\" not in param):
        return spec
    path = Path(param)
    stem = path.parent.name if path.stem in ("model", "checkpoint", "best_model") else path.stem
    return f"{name}:{stem or path.name}"


def _rolling_median(x: np.ndarray, window: int) -> np.ndarray:
    if window <= 1 or x.shape[-1] < window:
        return x
    from scipy.ndimage import median_filter

    return median_filter(x, size=window, mode="nearest", axes=(-1,))


def _save(plt, fig, out: str, name: str, dpi: int = 110) -> str:
    path = os.path.join(out, name)
    fig.savefig(path, dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    return path


def _plain_log_axis(axis) -> None:
    """Log scale with ticks written 0.05, 0.1, 0.2 instead of 5x10^-2."""
    from matplotlib.ticker import FuncFormatter, LogLocator

    fmt = FuncFormatter(lambda v, _: f"{v:g}")
    axis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
    axis.set_major_formatter(fmt)
    axis.set_minor_formatter(FuncFormatter(lambda v, _: ""))


def evaluation_plots(results: dict, out: str) -> list[str]:
    """``error_over_time.png``, ``boxplot.png`` and ``tradeoff.png`` of an evaluation."""
    plt = _pyplot()
    if plt is None:
        return []
    summary, episodes, dt = results["summary"], results["episodes"], results["dt_s"]
    main = [r for r in summary if r["group"] == "main"]
    traces = {r["policy"]: np.array([e["tag_error_trace"] for e in episodes if e["policy"] == r["policy"]])
              for r in main}
    return [_error_over_time(plt, main, traces, dt, out), _boxplot(plt, main, traces, out),
            _tradeoff(plt, summary, out)]


def _error_over_time(plt, main, traces, dt, out) -> str:
    # Small multiples with one shared y axis: one policy per panel, the median over seeds
    # (rolling median over SMOOTH_S) and the band between the seeds' quartiles.
    n = len(main)
    rows = -(-n // 4)
    cols = -(-n // rows)  # balanced: 5 panels as 3 + 2, not 4 + 1
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 2.4 * rows), sharex=True, sharey=True, squeeze=False)
    window = max(int(round(SMOOTH_S / dt)), 1)
    for ax, r in zip(axes.ravel(), main, strict=False):
        tr = _rolling_median(traces[r["policy"]], window)
        t = np.arange(tr.shape[1]) * dt
        q1, med, q3 = np.nanpercentile(tr, [25, 50, 75], axis=0)
        ax.fill_between(t, q1, q3, color="tab:blue", alpha=0.25, lw=0)
        ax.plot(t, med, color="tab:blue", lw=1.2)
        ax.set_title(short_label(r["policy"]) + (" (GT)" if r["uses_ground_truth"] else ""), fontsize=9)
        ax.grid(alpha=0.3)
    for k, ax in enumerate(axes.ravel()[n:], start=n):
        ax.set_visible(False)
        above = axes.ravel()[k - cols]  # the panel above an empty slot is the last of its column
        above.xaxis.set_tick_params(labelbottom=True)
        above.set_xlabel("time (s)")
    axes[0, 0].set_yscale("log")
    _plain_log_axis(axes[0, 0].yaxis)
    for ax in axes[-1][: n - cols * (rows - 1)]:
        ax.set_xlabel("time (s)")
    for ax in axes[:, 0]:
        ax.set_ylabel("tag error (m)")
    fig.suptitle(f"Tag error over time: median over seeds (line), quartiles (band); {SMOOTH_S:g} s rolling median",
                 fontsize=10)
    fig.tight_layout()
    return _save(plt, fig, out, "error_over_time.png")


def _boxplot(plt, main, traces, out) -> str:
    # The y range follows the useful policies: a policy whose box sits far above the others
    # (e.g. `never`/`always` at metres) is drawn off scale with its median written in.
    names = [short_label(r["policy"]) + (" (GT)" if r["uses_ground_truth"] else "") for r in main]
    data = [traces[r["policy"]].ravel() for r in main]
    data = [d[np.isfinite(d)] for d in data]
    q3 = np.array([np.percentile(d, 75) for d in data])
    typical = np.median(q3)
    off = q3 > 4 * typical
    whisk = [np.percentile(d, 75) + 1.5 * (np.percentile(d, 75) - np.percentile(d, 25)) for d in data]
    top = 1.1 * max((min(w, d.max()) for w, d, o in zip(whisk, data, off, strict=True) if not o), default=1.0)
    fig, ax = plt.subplots(figsize=(max(6.0, 1.0 * len(main)), 4.5))
    ax.boxplot(data, showfliers=False)
    ax.set_xticks(range(1, len(main) + 1), names, rotation=25, ha="right", fontsize=8)
    ax.set_ylim(0, top)
    for i, (d, o) in enumerate(zip(data, off, strict=True), start=1):
        if o:
            ax.annotate(f"off scale\nmedian {np.median(d):.2g} m", (i, top), xytext=(0, -4), textcoords="offset points",
                        ha="center", va="top", fontsize=7, color="tab:red")
    ax.set(ylabel="tag error per step (m)",
           title="Tag error distribution (box: quartiles; whiskers: 1.5 IQR; outliers not drawn)")
    ax.grid(axis="y", alpha=0.3)
    return _save(plt, fig, out, "boxplot.png")


def _sweep_param(spec: str) -> str:
    return spec.partition(":")[2]


def _tradeoff(plt, summary, out) -> str:
    # x on a symmetric log scale (0 = never calibrates; 1..60 per minute spread out), y linear
    # over the useful policies; points far above them (e.g. `always`) are listed, not drawn.
    from matplotlib.ticker import FixedLocator, FuncFormatter

    rows = [r for r in summary if r["calibrations_per_min"] >= 0 and np.isfinite(r["mean_tag_error_m"])]
    errs = np.array([r["mean_tag_error_m"] for r in rows])
    limit = 4 * np.median(errs)
    shown = [r for r in rows if r["mean_tag_error_m"] <= limit]
    hidden = [r for r in rows if r["mean_tag_error_m"] > limit]
    fig, ax = plt.subplots(figsize=(8, 5))
    for group, style, color, unit in (("fixed", "o-", "tab:gray", "steps"), ("threshold", "s-", "tab:olive", "m")):
        pts = sorted((r["calibrations_per_min"], r["mean_tag_error_m"], r["policy"]) for r in shown
                     if r["group"] == f"sweep_{group}")
        if len(pts) < 2:
            continue
        x, y, specs = zip(*pts, strict=True)
        ax.plot(x, y, style, color=color, ms=4, alpha=0.8, label=f"{group} sweep (labels: parameter, {unit})")
        for xi, yi, spec in zip(x, y, specs, strict=True):
            ax.annotate(_sweep_param(spec), (xi, yi), xytext=(3, -9), textcoords="offset points", fontsize=7,
                        color=color)
    markers = "*PXDv^<>ph"
    for i, r in enumerate(r for r in shown if r["group"] == "main"):
        ax.plot(r["calibrations_per_min"], r["mean_tag_error_m"], markers[i % len(markers)], ms=10, ls="none",
                label=short_label(r["policy"]) + (" (GT)" if r["uses_ground_truth"] else ""))
    ax.set_xscale("symlog", linthresh=1.0)
    ax.set_xlim(-0.2, 1.3 * max(r["calibrations_per_min"] for r in shown))
    ticks = [t for t in (0, 1, 2, 5, 10, 20, 50, 100) if t <= ax.get_xlim()[1]]
    ax.xaxis.set_major_locator(FixedLocator(ticks))
    ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    ax.xaxis.set_minor_formatter(FuncFormatter(lambda v, _: ""))
    ax.set(xlabel="calibrations per minute", ylabel="mean tag error (m)", title="Error vs calibration rate")
    ax.grid(alpha=0.3)
    if hidden:
        text = "off scale: " + ", ".join(f"{short_label(r['policy'])} ({r['mean_tag_error_m']:.2g} m)" for r in hidden)
        ax.text(0.0, -0.16, text, transform=ax.transAxes, fontsize=7, color="tab:red", va="top")
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0)
    return _save(plt, fig, out, "tradeoff.png")


# -- the paper reproduction (training/reproduce_paper.py) ---------------------------------------

def paper_figures(first: dict, anchors, tags, rotation, paper: dict, out: str, suffix: str) -> list[str]:
    """``paper_fig4*.png`` (one run's errors beside the paper's, one y scale per row) and
    ``paper_fig5*.png`` (box plots; the y range follows the boxes, outliers beyond it counted)."""
    plt = _pyplot()
    if plt is None:
        return []
    fig, axes = plt.subplots(2, 2, figsize=(12, 6), sharex=True, sharey="row")
    n = 55
    for i in range(first["anchor_error_m"].shape[1]):
        axes[0, 0].plot(first["anchor_error_m"][:n, i], marker=".", label=f"A{i + 1}")
    for i in range(first["tag_error_m"].shape[1]):
        axes[1, 0].plot(first["tag_error_m"][:n, i], marker=".", label=f"Tag{i + 1}")
    for name, values in paper["fig4_anchor_error_m"].items():
        axes[0, 1].plot(values, marker=".", label=name)
    for name, values in paper["fig4_tag_error_m"].items():
        axes[1, 1].plot(values, marker=".", label=name)
    axes[0, 0].set(title="uwb-env (one run)", ylabel="anchor position error (m)")
    axes[0, 1].set(title="paper, Fig. 4")
    axes[1, 0].set(ylabel="tag position error (m)", xlabel="simulation step")
    axes[1, 1].set(xlabel="simulation step")
    for ax in axes.ravel():
        ax.legend(fontsize=7, loc="upper left")
        ax.grid(alpha=0.3)
    fig.tight_layout()
    paths = [_save(plt, fig, out, f"paper_fig4{suffix}.png", dpi=100)]

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 5), gridspec_kw={"width_ratios": [2, 1]})
    paper_boxes = [paper["fig5_anchor_translation_error_m"], paper["fig5_tag_translation_error_m"]]
    _boxes_beside_paper(ax1, [np.asarray(anchors), np.asarray(tags)], paper_boxes, "pink",
                        ["anchors\n(ours)", "anchors\n(paper)", "tags\n(ours)", "tags\n(paper)"])
    ax1.set(ylabel="translation error (m)")
    _boxes_beside_paper(ax2, [np.asarray(rotation)], [paper["fig5_x_axis_rotation_error_rad"]], "bisque",
                        ["x axis\n(ours)", "x axis\n(paper)"])
    ax2.set(ylabel="rotation error (rad)")
    fig.suptitle("Fig. 5 reproduction: ours (many runs) beside the paper's box plots")
    fig.tight_layout()
    paths.append(_save(plt, fig, out, f"paper_fig5{suffix}.png", dpi=100))
    return paths


def _boxes_beside_paper(ax, ours: list[np.ndarray], theirs: list[dict], color: str, labels: list[str]) -> None:
    pos = [1 + 2 * i for i in range(len(ours))]
    stats = [_box(d) for d in ours]
    ax.bxp(stats, positions=pos, widths=0.6, patch_artist=True, boxprops={"facecolor": color}, showfliers=False)
    ax.bxp([_bxp(b) for b in theirs], positions=[p + 0.8 for p in pos], widths=0.6, patch_artist=True,
           boxprops={"facecolor": "lightblue"}, showfliers=False)
    ax.set_xticks([x for p in pos for x in (p, p + 0.8)], labels)
    lo = min(min(s["whislo"] for s in stats), min(b["whisker_low"] for b in theirs))
    hi = max(max(s["whishi"] for s in stats), max(b["whisker_high"] for b in theirs))
    pad = 0.08 * (hi - lo)
    ax.set_ylim(lo - pad, hi + pad)
    for p, d, s in zip(pos, ours, stats, strict=True):
        beyond = int(((d > hi + pad) | (d < lo - pad)).sum())
        if beyond:
            ax.annotate(f"{beyond} outliers\noff scale ({beyond / d.size:.1%})", (p + 0.32, hi + pad), xytext=(2, -3),
                        textcoords="offset points", ha="center", va="top", fontsize=7, color="tab:red")
    ax.grid(axis="y", alpha=0.3)


def _box(d: np.ndarray) -> dict:
    q1, med, q3 = np.percentile(d, [25, 50, 75])
    iqr = q3 - q1
    inside = d[(d >= q1 - 1.5 * iqr) & (d <= q3 + 1.5 * iqr)]
    return {"q1": q1, "med": med, "q3": q3, "whislo": inside.min(), "whishi": inside.max(), "fliers": []}


def _bxp(b: dict) -> dict:
    return {"label": "paper", "q1": b["q1"], "med": b["median"], "q3": b["q3"], "whislo": b["whisker_low"],
            "whishi": b["whisker_high"], "fliers": []}
