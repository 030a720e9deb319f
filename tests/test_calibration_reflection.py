"""First calibration: the paper frame's reflection is only as certain as its sign rule."""

import numpy as np

from uwb_env.localization import calibrate_anchors

SIGMA = 0.06


def _ranges(x, rng):
    d = np.linalg.norm(x[:, None] - x[None], axis=-1)
    noise = rng.normal(0.0, SIGMA, d.shape)
    r = d + np.triu(noise, 1) + np.triu(noise, 1).T
    np.fill_diagonal(r, 0.0)
    return r


def test_a_strip_with_anchors_on_both_sides_of_the_x_axis_is_flagged_and_a_square_is_not():
    rng = np.random.default_rng(0)
    # anchors 0 and 1 along a strip; the others +-1.5 m on either side: their y sum to ~0, so
    # the noise decides the frame's reflection
    strip = np.array([[0.0, 0.0], [30.0, 0.0], [5.0, 1.5], [10.0, -1.5], [20.0, 1.5], [25.0, -1.5]])
    square = np.array([[0.0, 0.0], [8.0, 0.0], [8.0, 8.0], [0.0, 8.0]])
    strip_flags = [calibrate_anchors(_ranges(strip, rng), range_std_m=SIGMA).ambiguous for _ in range(20)]
    square_flags = [calibrate_anchors(_ranges(square, rng), range_std_m=SIGMA).ambiguous for _ in range(20)]
    assert all(strip_flags)
    assert not any(square_flags)


def test_with_a_prior_the_reflection_comes_from_the_prior_and_is_not_flagged():
    rng = np.random.default_rng(1)
    strip = np.array([[0.0, 0.0], [30.0, 0.0], [5.0, 1.5], [10.0, -1.5], [20.0, 1.5], [25.0, -1.5]])
    res = calibrate_anchors(_ranges(strip, rng), range_std_m=SIGMA, prior=strip + 0.05)
    assert res.status == "ok" and not res.ambiguous
    assert np.abs(res.positions - strip).max() < 0.5
