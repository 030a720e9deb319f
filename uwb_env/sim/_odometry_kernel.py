"""Compiled step of :class:`~uwb_env.sim.odometry.OdometryModel` (the ``distance`` model).

One loop per robot instead of ~25 numpy calls. The complex products and magnitudes are
written out as numpy computes them (``_numpy_complex``), so a seed gives the same trajectory
to the last bit as the numpy version it replaced (tested on values recorded from it).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from uwb_env.sim._numpy_complex import fma, magnitude


@njit(cache=True)
def drift_step(delta, turn, noise, scale, gain, yaw_error, yaw_var_per_m, yaw_var_per_rad, noise_std, slip_gain2,
               heading_var, net, sum_a, sum_b, sum_c, dist_sum, steps, out):
    """Believed planar displacement of every robot for its true ``delta`` (n, >= 2) and
    ``turn`` (n,), written to ``out`` (n, 2); the yaw errors and the drift accumulators are
    updated in place. noise: 3n normals ([0, 2n) planar white noise, [2n, 3n) yaw);
    gain: per-robot noise multiplier (slips)."""
    n = delta.shape[0]
    for i in range(n):
        dx, dy = delta[i, 0], delta[i, 1]
        dist = magnitude(dx, dy)
        yaw_var = yaw_var_per_m * dist + yaw_var_per_rad * turn[i]
        yaw = yaw_error[i] + gain[i] * (math.sqrt(yaw_var) * noise[2 * n + i])
        yaw_error[i] = yaw
        white = gain[i] * noise_std * math.sqrt(dist)
        # scale * e^{i yaw} * d + white * (complex noise)
        ar, ai = scale[i] * math.cos(yaw), scale[i] * math.sin(yaw)
        er = fma(ar, dx, -(ai * dy)) + white * noise[2 * i]
        ei = fma(ar, dy, ai * dx) + white * noise[2 * i + 1]
        out[i, 0] = er
        out[i, 1] = ei
        # what the robot can predict of its own drift (OdometryModel._accumulate)
        dv = slip_gain2 * yaw_var
        heading_var[i] += dv
        pr, pi = net[i].real, net[i].imag
        sum_a[i] += dv
        sum_b[i] = complex(sum_b[i].real + dv * pr, sum_b[i].imag + dv * pi)
        sum_c[i] += dv * (pr * pr + pi * pi)
        net[i] = complex(pr + er, pi + ei)
        dist_sum[i] += magnitude(er, ei)
        steps[i] += 1.0


@njit(cache=True)
def drift_variance(net, sum_b, dist, h0, sum_a, sum_c, white_per_m, carried_base):
    """``OdometryModel.expected_drift_var_m2`` (distance model) for every robot: white noise
    ``white_per_m * d`` plus the heading part ``(s^2 + v0 + A) |P|^2 - 2 Re(P conj B) + C``,
    floored at 0."""
    n = net.shape[0]
    out = np.empty(n)
    for i in range(n):
        pr, pi = net[i].real, net[i].imag
        p2 = pr * pr + pi * pi
        cross = pr * sum_b[i].real + pi * sum_b[i].imag
        heading = (carried_base + h0[i] + sum_a[i]) * p2 - 2 * cross + sum_c[i]
        out[i] = white_per_m * dist[i] + max(heading, 0.0)
    return out
