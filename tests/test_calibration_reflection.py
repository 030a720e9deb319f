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


def test_unfold_skips_a_reflection_that_cannot_be_put_in_the_gauge(monkeypatch):
    """A single-anchor reflection that lands every anchor on one line cannot be put in the
    paper frame: unfold must skip that start (as the other starts are skipped), not raise out
    of calibrate_anchors (found by a review: a 4-anchor later round with a prior 3 m off)."""
    import uwb_env.localization.calibration as calibration

    def collinear(x, k):
        out = x.copy()
        out[:, 1] = 0.0
        out[:, 0] = np.arange(len(x), dtype=float) + 1.0  # not in the gauge already: put there first
        return out

    monkeypatch.setattr(calibration, "_reflect_anchor", collinear)
    rng = np.random.default_rng(2)
    truth = rng.uniform(0, 10, (5, 2))
    d = np.linalg.norm(truth[:, None] - truth[None], axis=2)
    d[0, 1] = d[1, 0] = d[0, 1] + 1.0  # a misfit the fit test rejects: unfold runs
    prior = truth + rng.normal(0, 0.1, truth.shape)
    res = calibrate_anchors(d, prior=prior, range_std_m=0.05)
    assert res.status == "poor_fit" and np.isfinite(res.positions).all()
