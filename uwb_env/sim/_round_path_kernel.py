"""Compiled linear interpolation of a round's recorded path (``round_path.RoundPath._at``).

A round's finish interpolates the path three times (the midpoint, each pair's time for the
carried means and for their variance); in numpy each took ~15 array calls on a handful of
numbers, a tenth of a single env's calibration step.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def interpolate(times, stack, t):
    """stack (T, R) given at increasing ``times`` (T >= 2), linearly interpolated at each of
    ``t`` (Q,) -> (Q, R); outside the recorded span the first or last segment extends (numpy's
    ``searchsorted(times, t, side="right") - 1`` clipped to [0, T - 2], the same arithmetic)."""
    n_times, n_cols = stack.shape
    out = np.empty((len(t), n_cols))
    for q in range(len(t)):
        tq = t[q]
        k = 0
        while k < n_times and times[k] <= tq:
            k += 1
        s = min(max(k - 1, 0), n_times - 2)
        w = (tq - times[s]) / max(times[s + 1] - times[s], 1e-12)
        for r in range(n_cols):
            out[q, r] = (1.0 - w) * stack[s, r] + w * stack[s + 1, r]
    return out
