"""Robot motion, vectorized over every robot in the world (anchors and tags together).

Each robot follows its group's :class:`~uwb_env.config.MotionConfig`:

- ``heading`` (the paper's model): keep a heading that random-walks; every move gets
  Gaussian noise.
- ``random_waypoint``: drive to a uniformly drawn waypoint, pause there, pick the next.
- ``stop_and_go``: ``heading`` plus random pauses (rate ``pause_rate_per_s``).
- ``static``: never moves.
- ``patrol``: random waypoints within ``patrol_radius_m`` of the robot's starting slot (a
  formation held around the work area).
- ``inside_hull``: random waypoints inside the polygon of the first group's (the anchors')
  starting slots.

Motion is planar (x, y); in 3D each robot keeps its height. Robots reflect off the walls of
the square area ``[0, L]^2``. One compiled loop (``_motion_kernel``) moves all robots, whatever
mix of models is configured: a step of one env costs two kernel calls instead of ~30 numpy
calls, and a step of thousands of copies one pass over memory.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from uwb_env.config import MotionConfig
from uwb_env.sim._motion_kernel import advance, waypoint_reach


class MotionModel:
    """Moves groups of robots; per-robot parameters are drawn at :meth:`reset`.

    Args:
        groups: ``(config, count)`` per group, in the order of the position rows.
        area_size_m: side of the square area.
        copies: independent copies of the scene stacked in every group (the batched env: the
            first ``count / copies`` rows of a group belong to copy 0, and so on). Formation
            models keep to their own copy's anchors (the first group).
    """

    def __init__(self, groups: Sequence[tuple[MotionConfig, int]], area_size_m: float, copies: int = 1):
        self.groups = [(cfg, int(count)) for cfg, count in groups]
        self.area_size_m = float(area_size_m)
        self.copies = int(copies)
        if self.copies < 1 or any(count % self.copies for _, count in self.groups):
            raise ValueError(f"copies={copies!r}: must be >= 1 and divide every group's count")
        self.positions = np.zeros((0, 2))

    def reset(self, positions: np.ndarray, rng: np.random.Generator) -> None:
        """Start from ``positions`` (n, dim); draw speeds, headings, waypoints per robot."""
        self.positions = np.array(positions, dtype=float)
        n = len(self.positions)
        counts = [count for _, count in self.groups]
        if sum(counts) != n:
            raise ValueError(f"positions has {n} rows, motion groups describe {sum(counts)}")

        def column(attr: str, dtype=float) -> np.ndarray:  # one value per group, repeated per robot
            return np.repeat(np.array([getattr(cfg, attr) for cfg, _ in self.groups], dtype=dtype), counts)

        lo, hi = column("speed_min_mps"), column("speed_max_mps")
        models = column("model", object).astype(str)
        static = models == "static"
        self.speeds = np.where(static, 0.0, rng.uniform(lo, hi))
        self.headings = rng.uniform(-np.pi, np.pi, n)
        self.heading_std = np.where(static, 0.0, column("heading_noise_std_rad_per_sqrt_s"))
        self.position_std = np.where(static, 0.0, column("position_noise_std_m_per_sqrt_s"))
        self.pause_rate = np.where(models == "stop_and_go", column("pause_rate_per_s"), 0.0)
        self.pause_min, self.pause_max = column("pause_min_s"), column("pause_max_s")
        self.waypoint_mask = np.isin(models, ("random_waypoint", "patrol", "inside_hull"))
        self.waypoints = rng.uniform(0.0, self.area_size_m, (n, 2)).view(np.complex128)[:, 0]
        # Formation models draw waypoints around home slots (kept from the start positions).
        self._patrol = models == "patrol"
        self._hull = models == "inside_hull"
        self._home = self.positions[:, :2].copy().view(np.complex128)[:, 0]
        self._radius = column("patrol_radius_m")
        self._hull_points = self._home[: self.groups[0][1]] if self.groups else self._home[:0]
        # copy of every row (formation models draw from their own copy's anchors)
        self._copy_of = np.concatenate([np.repeat(np.arange(self.copies), count // self.copies)
                                        for _, count in self.groups]) if self.groups else np.zeros(0, dtype=int)
        self._hull_by_copy = self._hull_points.reshape(self.copies, -1)
        if self._patrol.any() or self._hull.any():
            rows = self._patrol | self._hull
            self.waypoints[rows] = self._draw_waypoints(rows, rng)
        self.pause_left_s = np.zeros(n)
        self._any_waypoint = bool(self.waypoint_mask.any())
        self._any_pause_rate = bool((self.pause_rate > 0).any())
        self._all_static = bool(static.all())
        self._any_pauses = self._any_waypoint or self._any_pause_rate
        # placeholders the kernel reads only when waypoints / pauses exist
        self._no_waypoints = (np.zeros(n, dtype=np.complex128), np.zeros(n), np.zeros(n, dtype=bool))
        self._all_moving = np.ones(n, dtype=bool)

    def step(self, dt_s: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """Advance by ``dt_s``; return (displacement (n, dim), absolute heading change (n,))."""
        pos = self.positions
        n, dim = pos.shape
        if self._all_static or n == 0:
            return np.zeros((n, dim)), np.zeros(n)
        # Draws in bulk, in a fixed order (noise, then arrivals, then pause starts); the
        # per-robot arithmetic is one compiled loop (``_motion_kernel``).
        noise = rng.standard_normal(3 * n)
        if self._any_waypoint:
            to_wp, dist, reached, any_reached = waypoint_reach(pos, self.waypoints, self.waypoint_mask, self.speeds,
                                                               dt_s, self.pause_left_s)
            if any_reached:  # arrive exactly, pause there, and aim at the next waypoint afterwards
                self.pause_left_s[reached] = rng.uniform(self.pause_min[reached], self.pause_max[reached])
                self.waypoints[reached] = self._draw_waypoints(reached, rng)
        else:
            to_wp, dist, reached = self._no_waypoints
        moving = self._all_moving
        if self._any_pauses:
            moving = self.pause_left_s <= 0.0
            if self._any_pause_rate:
                self._start_pauses(~moving, dt_s, rng)
        delta = np.zeros((n, dim))
        turn = np.empty(n)
        advance(pos, self.headings, self.speeds, self.heading_std, self.position_std, noise, float(dt_s),
                self.area_size_m, self._any_waypoint, self.waypoint_mask, to_wp, dist, reached, self._any_pauses,
                moving, self.pause_left_s, delta, turn)
        return delta, turn

    def command(self, rows: np.ndarray, headings_rad: np.ndarray, speeds_mps: np.ndarray) -> None:
        """Override the scripted motion of robots ``rows``: steer to ``headings_rad`` at
        ``speeds_mps`` (0 = stop). Heading noise still applies; used by learned anchor motion."""
        self.headings[rows] = headings_rad
        self.speeds[rows] = speeds_mps
        self.waypoint_mask[rows] = False
        self.pause_rate[rows] = 0.0
        self.pause_left_s[rows] = 0.0
        self._all_static = False
        self._any_waypoint = bool(self.waypoint_mask.any())
        self._any_pause_rate = bool((self.pause_rate > 0).any())
        self._any_pauses = self._any_waypoint or self._any_pause_rate

    def _draw_waypoints(self, rows: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Next waypoints (complex) of the robots in ``rows``, by each robot's model."""
        k = int(rows.sum())
        out = rng.uniform(0.0, self.area_size_m, (k, 2)).view(np.complex128)[:, 0]
        patrol, hull = self._patrol[rows], self._hull[rows]
        if patrol.any():  # uniform in the disc around the home slot
            m = int(patrol.sum())
            r = self._radius[rows][patrol] * np.sqrt(rng.random(m))
            out[patrol] = self._home[rows][patrol] + r * np.exp(2j * np.pi * rng.random(m))
        per_copy = self._hull_by_copy.shape[1]
        if hull.any() and per_copy >= 3:  # convex combinations of the slots (of the robot's own copy)
            w = rng.dirichlet(np.ones(per_copy), int(hull.sum()))
            if self.copies == 1:
                out[hull] = w @ self._hull_points
            else:
                out[hull] = np.einsum("kn,kn->k", w, self._hull_by_copy[self._copy_of[rows][hull]])
        flat = np.clip(out.view(np.float64), 0.0, self.area_size_m)
        return flat.view(np.complex128)

    def _start_pauses(self, paused: np.ndarray, dt_s: float, rng: np.random.Generator) -> None:
        # Start a pause with probability rate * dt (Poisson-process discretization).
        start = (~paused) & (rng.random(len(paused)) < self.pause_rate * dt_s)
        if start.any():
            self.pause_left_s[start] = rng.uniform(self.pause_min[start], self.pause_max[start])

