"""The anchors' feature kernel shared by the single and the batched env, against numpy."""

import numpy as np

from uwb_env.features import anchor_features


def test_anchor_features_match_numpy_and_stay_in_bounds(rng):
    b, n, w, dim = 5, 4, 6, 2
    anchors = rng.uniform(-5, 25, (b, n, dim))
    anchors[0, 0, 0] = 1e6  # far outside: clipped
    time_since = rng.uniform(0, 100, (b, n))
    pred_var, calib_var = rng.uniform(0, 0.5, (b, n)), rng.uniform(0, 0.1, (b, n))
    calib_var[1, 2] = -1e-18  # rounding below zero: a std of 0, not NaN
    last_rms = rng.uniform(0, 0.3, b)
    tag_hist, anchor_hist = rng.uniform(0, 1, (b, w)), rng.uniform(0, 1, (b, w, n))
    filled = np.array([0, 1, 3, 6, 6])
    calibrating = np.array([0.0, 1.0, 0.0, 1.0, 0.0])
    progress = np.array([0.0, 0.4, 0.0, 0.9, 0.0])
    low = np.array([-20, -20, 0, 0, 0, 0, 0, 0, 0, 0], dtype=np.float32)
    high = np.array([60, 60, 500, 10, 10, 10, 10, 10, 1, 1], dtype=np.float32)
    got = anchor_features(anchors, time_since, pred_var, calib_var, last_rms, tag_hist, anchor_hist, filled,
                          calibrating, progress, low, high)
    idx = np.arange(w)[None, :] < filled[:, None]
    tag_res = np.where(idx, tag_hist, 0.0).sum(1) / np.maximum(filled, 1)
    own = np.where(idx[..., None], anchor_hist, 0.0).sum(1) / np.maximum(filled, 1)[:, None]
    want = np.empty((b, n, dim + 8), dtype=np.float32)
    want[..., :2] = anchors
    want[..., 2] = time_since
    want[..., 3] = np.sqrt(np.maximum(pred_var, 0))
    want[..., 4] = np.sqrt(np.maximum(calib_var, 0))
    want[..., 5] = last_rms[:, None]
    want[..., 6] = tag_res[:, None]
    want[..., 7] = own
    want[..., 8] = calibrating[:, None]
    want[..., 9] = progress[:, None]
    want = np.clip(want, low, high)
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got, want)
    assert (got >= low).all() and (got <= high).all() and got[0, 0, 0] == 60
