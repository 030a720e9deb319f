"""Missing pairs (30 % dropped, graph rigid): noise-free ranges whose deterministic starts
(trilateration, MDS on the shortest-path fill, SMACOF from MDS) all fall into a fold. The
solver must still find the exact shape (cost ~0, status ok), not report a poor fit."""

import numpy as np
import pytest

from uwb_env.localization import aligned_errors, calibrate_anchors

CASES = [{"x": [[1.267, 18.011], [19.726, 10.228], [4.506, 10.876], [13.925, 9.644], [7.051, 4.956], [5.937, 0.996], [5.101, 19.063], [0.162, 14.549]], "missing": [[0, 6], [1, 5], [1, 6], [2, 4], [2, 5], [2, 7], [3, 7], [4, 6], [5, 7]]}, {"x": [[1.016, 0.88], [3.056, 12.113], [15.627, 9.597], [12.275, 12.851], [0.386, 4.926], [19.955, 6.616], [18.933, 9.846], [4.451, 0.048]], "missing": [[0, 1], [0, 7], [1, 2], [1, 4], [3, 4], [3, 5], [4, 5], [5, 7]]}, {"x": [[19.495, 13.039], [4.367, 12.553], [15.355, 8.463], [3.356, 7.034], [15.631, 4.154], [0.228, 17.581], [19.435, 17.378], [16.024, 14.593]], "missing": [[0, 5], [1, 5], [1, 6], [1, 7], [2, 5], [2, 6], [3, 5], [3, 7], [6, 7]]}]  # noqa: E501 (recorded cases)


@pytest.mark.parametrize("case", CASES)
def test_noise_free_missing_pairs_find_the_exact_shape(case):
    x = np.array(case["x"])
    d = np.linalg.norm(x[:, None] - x[None], axis=-1)
    for i, j in case["missing"]:
        d[i, j] = d[j, i] = np.nan
    np.fill_diagonal(d, np.nan)
    res = calibrate_anchors(d, range_std_m=0.05)
    assert res.status == "ok" and res.converged
    assert res.cost < 1e-6
    assert aligned_errors(res.positions, x).max() < 1e-4
