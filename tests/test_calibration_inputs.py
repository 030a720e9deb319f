"""Item 9 of issue 13 for tag fixes: bad input to locate_tags raises a typed error naming the
field (it returned NaN positions, a plain ValueError, or silently dropped an inf range)."""

import numpy as np
import pytest

from uwb_env.localization import InvalidPositionError, InvalidRangeError, LocalizationError, locate_tags

ANCHORS = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [10.0, 10.0]])
TAG = np.array([3.0, 4.0])
RANGES = np.linalg.norm(ANCHORS - TAG, axis=1)[None]


def test_clean_fix_still_works_and_nan_means_missing():
    fix = locate_tags(ANCHORS, RANGES, 0.05)
    assert np.allclose(fix.positions[0], TAG, atol=1e-6)
    r = RANGES.copy()
    r[0, 3] = np.nan
    assert np.allclose(locate_tags(ANCHORS, r, 0.05).positions[0], TAG, atol=1e-6)
    std = np.full(r.shape, 0.05)
    std[0, 3] = np.nan  # a missing range's std does not matter
    assert np.allclose(locate_tags(ANCHORS, r, std).positions[0], TAG, atol=1e-6)


@pytest.mark.parametrize("std", [0.0, np.nan, -0.1, np.inf])
def test_bad_std_is_typed(std):
    with pytest.raises(InvalidRangeError, match="range_std_m"):
        locate_tags(ANCHORS, RANGES, std)


@pytest.mark.parametrize("value", [-1.0, np.inf])
def test_bad_range_is_typed(value):
    r = RANGES.copy()
    r[0, 1] = value
    with pytest.raises(InvalidRangeError, match="ranges_m"):
        locate_tags(ANCHORS, r, 0.05)


def test_nan_anchor_is_typed():
    a = ANCHORS.copy()
    a[2, 0] = np.nan
    with pytest.raises(InvalidPositionError, match="anchors"):
        locate_tags(a, RANGES, 0.05)
    assert issubclass(InvalidPositionError, LocalizationError)
