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
def _variance(pr, pi, br, bi, dist, h0, sum_a, sum_c, white_per_m, carried_base):
    """White noise ``white_per_m * d`` plus the heading part ``(s^2 + v0 + A) |P|^2 -
    2 Re(P conj B) + C`` (P = pr + i pi, B = br + i bi), floored at 0."""
    p2 = pr * pr + pi * pi
    cross = pr * br + pi * bi
    heading = (carried_base + h0 + sum_a) * p2 - 2 * cross + sum_c
    return white_per_m * dist + max(heading, 0.0)


@njit(cache=True)
def drift_variance(net, sum_b, dist, h0, sum_a, sum_c, white_per_m, carried_base):
    """``OdometryModel.expected_drift_var_m2`` (distance model) for every robot (1-D arrays)."""
    n = net.shape[0]
    out = np.empty(n)
    for i in range(n):
        out[i] = _variance(net[i].real, net[i].imag, sum_b[i].real, sum_b[i].imag, dist[i], h0[i], sum_a[i],
                           sum_c[i], white_per_m, carried_base)
    return out


@njit(cache=True)
def _recentre(psr, psi, s_a, s_br, s_bi, s_c, s_dist, p_r, p_i, a, b_r, b_i, c, dist):
    """Accumulators (P, A, B, C, d) re-centred on a snapshot's (P_s = psr + i psi, A_s, B_s, C_s,
    d_s): P - P_s, A - A_s, (B - B_s) - (A - A_s) P_s, (C - C_s) - 2 Re(conj(P_s) (B - B_s)) +
    (A - A_s) |P_s|^2, d - d_s; each operation as numpy computes it on the arrays (a real times
    a complex included), so the numbers are the numpy version's to the last bit."""
    d_a = a - s_a
    d_br, d_bi = b_r - s_br, b_i - s_bi
    cross = psr * d_br + psi * d_bi
    c_out = (c - s_c) - 2.0 * cross + d_a * (psr * psr + psi * psi)
    b_out_r, b_out_i = d_br - (d_a * psr - 0.0 * psi), d_bi - (d_a * psi + 0.0 * psr)
    return p_r - psr, p_i - psi, d_a, b_out_r, b_out_i, c_out, dist - s_dist


@njit(cache=True)
def recentre(since_net, since_a, since_b, since_c, since_dist, net, a, b, c, dist):
    """``_recentre`` for every robot (1-D arrays): returns the re-centred net (complex), A, B
    (complex), C and distance."""
    n = net.shape[0]
    out_net = np.empty(n, np.complex128)
    out_a, out_b, out_c, out_d = np.empty(n), np.empty(n, np.complex128), np.empty(n), np.empty(n)
    for i in range(n):
        pr, pi, ra, rbr, rbi, rc, rd = _recentre(since_net[i].real, since_net[i].imag, since_a[i], since_b[i].real,
                                                 since_b[i].imag, since_c[i], since_dist[i], net[i].real,
                                                 net[i].imag, a[i], b[i].real, b[i].imag, c[i], dist[i])
        out_net[i] = complex(pr, pi)
        out_a[i], out_b[i], out_c[i], out_d[i] = ra, complex(rbr, rbi), rc, rd
    return out_net, out_a, out_b, out_c, out_d


@njit(cache=True)
def drift_variance_between(heading_var, net, sum_a, sum_b, sum_c, dist, earlier, later, white_per_m,
                           carried_base):
    """Drift variance accrued from snapshot ``earlier[q]`` to snapshot ``later[q]`` by every
    robot: the accumulators (T, n) of T snapshots re-centred on the earlier one (``_recentre``,
    the heading variance then carried) and ``_variance``. Returns (Q, n)."""
    n = net.shape[1]
    out = np.empty((len(earlier), n))
    for q in range(len(earlier)):
        e, f = earlier[q], later[q]
        for i in range(n):
            pr, pi, ra, rbr, rbi, rc, rd = _recentre(
                net[e, i].real, net[e, i].imag, sum_a[e, i], sum_b[e, i].real, sum_b[e, i].imag, sum_c[e, i],
                dist[e, i], net[f, i].real, net[f, i].imag, sum_a[f, i], sum_b[f, i].real, sum_b[f, i].imag,
                sum_c[f, i], dist[f, i])
            out[q, i] = _variance(pr, pi, rbr, rbi, rd, heading_var[e, i], ra, rc, white_per_m, carried_base)
    return out


@njit(cache=True)
def add_rotated(estimates, displacement, rot):
    """estimates (B, N, 2) += each copy's displacement (B, N, 2) rotated by rot (B, 2, 2) into
    its estimate frame, in place: ``np.einsum("bnj,bij->bni", displacement, rot)``'s numbers
    (the same two products summed in the same order; tested equal) without its ~1 ms at B = 4096."""
    for b in range(displacement.shape[0]):
        r00, r01, r10, r11 = rot[b, 0, 0], rot[b, 0, 1], rot[b, 1, 0], rot[b, 1, 1]
        for k in range(displacement.shape[1]):
            x, y = displacement[b, k, 0], displacement[b, k, 1]
            estimates[b, k, 0] += x * r00 + y * r01
            estimates[b, k, 1] += x * r10 + y * r11


@njit(cache=True)
def slip_step(slip_left, noise, q, any_slip, dt, duration, multiplier, gain):
    """One step of the slips: a robot not slipping starts one where its normal
    ``noise[3n + i]`` exceeds ``q``; the time left shrinks by dt. Nothing is touched while
    nobody slips (``any_slip``) or starts to: returns (False, False). Otherwise ``slip_left``
    (n,) is updated in place, ``gain`` (n,) receives each robot's noise multiplier for this
    step (``multiplier`` where it was slipping, else 1) and (True, whether anyone still slips)
    is returned."""
    n = slip_left.shape[0]
    if not any_slip:
        starts = False
        for i in range(n):
            if noise[3 * n + i] > q:
                starts = True
                break
        if not starts:
            return False, False
    still = False
    for i in range(n):
        slipping = slip_left[i] > 0.0
        left = max(slip_left[i] - dt, 0.0)
        if noise[3 * n + i] > q and not slipping:
            left = duration
        slip_left[i] = left
        still = still or left > 0.0
        gain[i] = multiplier if slipping else 1.0
    return True, still
