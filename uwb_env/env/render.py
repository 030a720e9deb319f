"""Matplotlib rendering (imported only when a render mode is set).

Left: true anchors (filled squares) and their estimates (hollow), tags (dots) and their fixes
(crosses), the calibration links while a round runs (like the paper's Fig. 1). Right: the
mean anchor and tag error over time, calibration periods shaded.
"""

from __future__ import annotations

import numpy as np


class Renderer:
    def __init__(self, config, render_mode: str):
        try:
            import matplotlib
        except ImportError as err:  # pragma: no cover - depends on the install
            raise ImportError("rendering needs matplotlib: pip install 'uwb-env[plot]'") from err
        if render_mode == "rgb_array":
            matplotlib.use("Agg", force=False)
        import matplotlib.pyplot as plt

        self.plt = plt
        self.mode = render_mode
        self.config = config
        self.fig, (self.ax_map, self.ax_err) = plt.subplots(1, 2, figsize=(10, 4.5), dpi=80)

    def draw(self, system, history):
        ax, size = self.ax_map, self.config.sim.area_size_m
        ax.clear()
        truth = system.world.to_estimate_frame(system.world.anchors_true)
        est = system.world.anchors_est
        tags = system.world.to_estimate_frame(system.world.tags_true)
        links = system.last_round_links
        if links is not None:
            for i, j in {tuple(sorted(p)) for p in links.tolist()}:
                ax.plot(*est[[i, j], :2].T, color="orange", lw=0.8, alpha=0.6)
        ax.scatter(*truth[:, :2].T, marker="s", c="tab:blue", label="anchor (true)")
        ax.scatter(*est[:, :2].T, marker="s", facecolors="none", edgecolors="tab:blue", label="anchor (estimate)")
        if len(tags):
            ax.scatter(*tags[:, :2].T, c="tab:green", s=15, label="tag (true)")
            ax.scatter(*system.tag_fix[:, :2].T, marker="x", c="tab:red", label="tag fix")
        for i, p in enumerate(est):
            ax.annotate(str(i), p[:2], fontsize=8)
        pad = 0.3 * size
        lo = min(truth[:, 0].min(), 0) - pad
        ax.set_xlim(lo, max(truth[:, 0].max(), size) + pad)
        ax.set_ylim(min(truth[:, 1].min(), 0) - pad, max(truth[:, 1].max(), size) + pad)
        ax.set_aspect("equal")
        ax.set_title(f"t = {system.world.time_s:.1f} s, calibrations: {system.calibration_count}")
        ax.legend(loc="upper right", fontsize=7)
        ax = self.ax_err
        ax.clear()
        steps = np.arange(len(history.get("tag_error_m", [])))
        if len(steps):
            ax.plot(steps, history["anchor_error_m"], label="mean anchor error")
            ax.plot(steps, history["tag_error_m"], label="mean tag error")
            cal = np.asarray(history["calibrating"]) > 0
            ax.fill_between(steps, 0, 1, where=cal, color="orange", alpha=0.2, transform=ax.get_xaxis_transform(),
                            label="calibrating")
        ax.set_xlabel("step")
        ax.set_ylabel("error (m)")
        ax.legend(loc="upper left", fontsize=7)
        self.fig.tight_layout()
        if self.mode == "human":
            self.plt.pause(0.001)
            return None
        self.fig.canvas.draw()
        return np.asarray(self.fig.canvas.buffer_rgba())[..., :3].copy()

    def close(self) -> None:
        self.plt.close(self.fig)
