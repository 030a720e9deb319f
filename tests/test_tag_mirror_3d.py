"""3D mirror check: a fix and its reflection across the anchors' plane."""

import numpy as np

from uwb_env.localization.multilateration import TAG_AMBIGUOUS, TAG_NO_FIX, TAG_OK, check_mirror_3d

ANCHORS = np.array([[0.0, 0.0, 0.0], [8.0, 0.0, 0.3], [8.0, 8.0, 0.0], [0.0, 8.0, 2.0]])
SIGMA = 0.05


def _ranges(tag):
    return np.linalg.norm(ANCHORS - tag, axis=1)


def test_a_fix_on_the_wrong_side_is_switched_when_the_ranges_reject_it():
    tag = np.array([3.0, 4.0, 2.5])
    ranges = _ranges(tag)[None]
    normal = np.linalg.svd(ANCHORS - ANCHORS.mean(0))[2][-1]
    wrong = tag - 2.0 * ((tag - ANCHORS.mean(0)) @ normal) * normal  # the reflection
    positions, status, switched = check_mirror_3d(ANCHORS, wrong[None], ranges, SIGMA**2)
    assert switched[0] and status[0] == TAG_OK
    np.testing.assert_allclose(positions[0], tag, atol=1e-3)
    # the right fix stays and is not flagged
    positions, status, switched = check_mirror_3d(ANCHORS, tag[None], ranges, SIGMA**2)
    assert not switched[0] and status[0] == TAG_OK
    np.testing.assert_allclose(positions[0], tag)


def test_coplanar_anchors_fit_both_sides_exactly_and_the_fix_is_flagged_ambiguous():
    anchors = ANCHORS * np.array([1.0, 1.0, 0.0])  # all at one height: up and down are the same ranges
    tag = np.array([3.0, 4.0, 1.5])
    ranges = np.linalg.norm(anchors - tag, axis=1)[None]
    positions, status, switched = check_mirror_3d(anchors, tag[None], ranges, SIGMA**2)
    assert status[0] == TAG_AMBIGUOUS and not switched[0]
    np.testing.assert_allclose(positions[0], tag)


def test_tags_without_a_fix_are_reported_as_such():
    positions = np.array([[np.nan] * 3, [3.0, 4.0, 1.0]])
    ranges = np.stack([_ranges(np.array([1.0, 1.0, 1.0])), _ranges(positions[1])])
    _, status, switched = check_mirror_3d(ANCHORS, positions, ranges, SIGMA**2)
    assert status[0] == TAG_NO_FIX and not switched.any()
