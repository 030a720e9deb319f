"""Compiled loops of :class:`~uwb_env.sim.motion.MotionModel` (one env or thousands of copies).

A step of a few robots was ~30 numpy calls (interpreter overhead, not arithmetic), and of
thousands of copies ~30 passes over memory; one loop per robot does both in one pass. Random
numbers stay with the caller's ``numpy.random.Generator`` (drawn in bulk, in the same order as
before), so a seed still fixes the trajectory. The maths is the model's: planar motion in
complex numbers, waypoint steering, pauses, reflection off the walls of ``[0, size]^2``.
"""

from __future__ import annotations

import cmath
import math

import numpy as np
from numba import njit

from uwb_env.sim._numpy_complex import magnitude


@njit(cache=True)
def waypoint_reach(pos, waypoints, waypoint_mask, speeds, dt_s, pause_left_s):
    """Per robot: the vector to its waypoint (complex), its length, and whether a waypoint
    robot that is not pausing reaches it this step. Returns (to_wp, dist, reached, any reached)."""
    n = pos.shape[0]
    to_wp = np.empty(n, dtype=np.complex128)
    dist = np.empty(n)
    reached = np.zeros(n, dtype=np.bool_)
    any_reached = False
    for i in range(n):
        t = waypoints[i] - complex(pos[i, 0], pos[i, 1])
        to_wp[i] = t
        d = magnitude(t.real, t.imag)  # numpy's |z| (the waypoint distance is stepped exactly)
        dist[i] = d
        if waypoint_mask[i] and d <= speeds[i] * dt_s and pause_left_s[i] <= 0.0:
            reached[i] = True
            any_reached = True
    return to_wp, dist, reached, any_reached


@njit(cache=True)
def advance(pos, headings, speeds, heading_std, position_std, noise, dt_s, size,
            steer, waypoint_mask, to_wp, dist, reached, pauses, moving, pause_left_s, delta, turn):
    """Move every robot one step, in place (``pos`` planar columns, ``headings``,
    ``pause_left_s``); write the displacement to ``delta`` (n, dim) and the absolute heading
    change to ``turn``.

    noise: 3n standard normals ([0, 2n) the planar jitter, [2n, 3n) heading increments).
    steer: waypoint robots exist (their headings point at ``to_wp``; a robot that ``reached``
    its waypoint steps exactly ``dist``). pauses: robots pause (``moving`` says who moves this
    step; every pause shortens by dt). A robot leaving the area is reflected off the wall."""
    n = pos.shape[0]
    sqrt_dt = math.sqrt(dt_s)
    new_x = np.empty(n)
    new_y = np.empty(n)
    old = headings.copy()
    outside = False
    for i in range(n):
        inc = heading_std[i] * sqrt_dt * noise[2 * n + i]
        turn[i] = abs(inc)
        heading = old[i] + inc
        step_len = speeds[i] * dt_s
        jitter = position_std[i] * sqrt_dt
        if steer:
            if reached[i]:
                step_len = dist[i]
            if waypoint_mask[i]:
                heading = math.atan2(to_wp[i].imag, to_wp[i].real)
        if pauses:
            pause_left_s[i] = max(pause_left_s[i] - dt_s, 0.0)
            if not moving[i]:
                step_len = 0.0
                jitter = 0.0
        e = cmath.exp(1j * heading)
        x = pos[i, 0] + step_len * e.real + jitter * noise[2 * i]
        y = pos[i, 1] + step_len * e.imag + jitter * noise[2 * i + 1]
        new_x[i] = x
        new_y[i] = y
        headings[i] = heading
        if x < 0.0 or x > size or y < 0.0 or y > size:
            outside = True
    # Waypoints and walls turn robots by more than the noise: then the turn is the wrapped
    # heading change; otherwise the noise increment itself (already written).
    for i in range(n):
        x, y, heading = new_x[i], new_y[i], headings[i]
        if outside:
            if x < 0.0 or x > size:
                x = min(max(-x if x < 0.0 else 2.0 * size - x, 0.0), size)
                heading = math.pi - heading
            if y < 0.0 or y > size:
                y = min(max(-y if y < 0.0 else 2.0 * size - y, 0.0), size)
                heading = -heading
            headings[i] = heading
        if steer or outside:
            turn[i] = abs((heading - old[i] + math.pi) % (2.0 * math.pi) - math.pi)
        delta[i, 0] = x - pos[i, 0]
        delta[i, 1] = y - pos[i, 1]
        pos[i, 0] = x
        pos[i, 1] = y
