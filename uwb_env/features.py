"""The anchors' observation features (``system.OBS_FIELDS``), one compiled kernel for the single
env (a batch of one) and the batched env.

Per anchor: its estimated position, then time since its last calibration, predicted and
calibration position std, the last calibration's RMS residual and the tags' mean fix residual
(shared by the team), its own mean range residual, whether a round runs and its progress. The
residual terms are means over the last ``filled`` steps of a ring buffer. Each value is cast
to float32 first and then clipped into the declared bounds, so the result is always inside the
observation space.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True)
def anchor_features(anchors_est, time_since_s, predicted_var, calibration_var, last_rms, tag_hist, anchor_hist,
                    filled, calibrating, progress, low, high):
    """anchors_est (B, N, D); time_since_s, predicted_var, calibration_var (B, N); last_rms (B,);
    tag_hist (B, W), anchor_hist (B, W, N) residual ring buffers with ``filled`` (B,) valid slots
    from the start; calibrating, progress (B,); low, high (D + 8,) float32 bounds.
    Returns (B, N, D + 8) float32."""
    b_count, n, dim = anchors_est.shape
    out = np.empty((b_count, n, dim + 8), np.float32)
    values = np.empty(dim + 8)
    for b in range(b_count):
        f = filled[b]
        tag_res = 0.0
        for w in range(f):
            tag_res += tag_hist[b, w]
        if f:
            tag_res /= f
        for k in range(n):
            own = 0.0
            for w in range(f):
                own += anchor_hist[b, w, k]
            if f:
                own /= f
            for a in range(dim):
                values[a] = anchors_est[b, k, a]
            values[dim] = time_since_s[b, k]
            values[dim + 1] = math.sqrt(max(predicted_var[b, k], 0.0))
            values[dim + 2] = math.sqrt(max(calibration_var[b, k], 0.0))
            values[dim + 3] = last_rms[b]
            values[dim + 4] = tag_res
            values[dim + 5] = own
            values[dim + 6] = calibrating[b]
            values[dim + 7] = progress[b]
            for j in range(dim + 8):
                v = np.float32(values[j])
                if v < low[j]:
                    v = low[j]
                if v > high[j]:
                    v = high[j]
                out[b, k, j] = v
    return out
