"""Missing pairs (30-40 % dropped, graph globally rigid): noise-free ranges whose
deterministic starts (trilateration, MDS on the shortest-path fill, SMACOF from MDS) all fall
into a fold. The solver must still find the exact shape (cost ~0, status ok), not report a poor
fit, nor a fold that the fit test lets through as ok."""

import numpy as np
import pytest

from uwb_env.localization import LocalizationError, aligned_errors, calibrate_anchors

CASES = [{"x": [[1.267, 18.011], [19.726, 10.228], [4.506, 10.876], [13.925, 9.644], [7.051, 4.956], [5.937, 0.996], [5.101, 19.063], [0.162, 14.549]], "missing": [[0, 6], [1, 5], [1, 6], [2, 4], [2, 5], [2, 7], [3, 7], [4, 6], [5, 7]]}, {"x": [[1.016, 0.88], [3.056, 12.113], [15.627, 9.597], [12.275, 12.851], [0.386, 4.926], [19.955, 6.616], [18.933, 9.846], [4.451, 0.048]], "missing": [[0, 1], [0, 7], [1, 2], [1, 4], [3, 4], [3, 5], [4, 5], [5, 7]]}, {"x": [[19.495, 13.039], [4.367, 12.553], [15.355, 8.463], [3.356, 7.034], [15.631, 4.154], [0.228, 17.581], [19.435, 17.378], [16.024, 14.593]], "missing": [[0, 5], [1, 5], [1, 6], [1, 7], [2, 5], [2, 6], [3, 5], [3, 7], [6, 7]]}]  # noqa: E501 (recorded cases)

# 10 anchors, 40 % of pairs dropped: before the build-up starts, 5 of these 7 ended in a fold
# 3.6-19.5 m off the truth, 3 of them with status "ok" (cost 4.7-5.9 at a 5 cm range std)
CASES += [{"x": [[11.751, 13.123], [4.057, 18.716], [16.111, 2.905], [4.398, 0.043], [18.788, 3.487], [16.676, 10.232], [1.142, 4.229], [5.154, 15.287], [7.353, 2.839], [18.927, 10.29]], "missing": [[0, 1], [0, 5], [0, 7], [1, 7], [2, 3], [2, 4], [2, 7], [2, 9], [3, 4], [3, 8], [4, 6], [4, 8], [5, 6], [6, 8]]}, {"x": [[16.345, 8.653], [7.156, 3.954], [16.041, 10.109], [17.523, 9.869], [17.501, 14.451], [11.394, 14.76], [14.702, 0.933], [16.182, 2.17], [10.81, 9.726], [15.236, 4.37]], "missing": [[0, 3], [0, 9], [1, 4], [1, 7], [1, 8], [2, 3], [2, 4], [2, 5], [2, 6], [2, 8], [4, 7], [5, 6], [5, 7], [5, 9], [6, 7], [6, 8], [7, 8]]}, {"x": [[14.988, 16.738], [19.669, 18.544], [9.373, 9.983], [10.498, 0.025], [9.361, 14.177], [1.168, 5.72], [2.855, 1.959], [6.579, 8.855], [2.372, 13.016], [13.167, 19.913]], "missing": [[0, 2], [0, 3], [0, 4], [0, 8], [0, 9], [1, 3], [1, 8], [1, 9], [2, 3], [2, 8], [3, 6], [3, 7], [3, 8], [4, 5], [4, 6], [5, 7], [5, 8], [5, 9], [6, 7], [6, 9], [7, 8]]}, {"x": [[10.331, 17.349], [1.409, 3.682], [5.831, 16.5], [4.589, 6.455], [10.265, 16.297], [15.309, 1.418], [8.085, 18.314], [8.254, 3.968], [2.634, 8.297], [12.763, 19.287]], "missing": [[0, 1], [0, 8], [0, 9], [1, 2], [1, 4], [1, 8], [2, 3], [2, 5], [2, 6], [2, 7], [3, 5], [3, 6], [3, 7], [3, 9], [4, 8], [5, 7], [6, 7], [6, 8]]}, {"x": [[4.287, 2.643], [16.756, 1.558], [4.636, 7.14], [0.116, 15.722], [8.794, 6.76], [6.58, 10.89], [9.214, 3.248], [9.035, 5.849], [12.371, 13.811], [2.21, 0.18]], "missing": [[0, 1], [0, 3], [0, 6], [0, 7], [1, 2], [1, 5], [1, 9], [2, 3], [2, 4], [2, 5], [2, 8], [3, 5], [3, 6], [3, 8], [3, 9], [4, 5], [4, 6], [4, 7], [4, 8], [5, 7], [5, 8]]}, {"x": [[12.237, 0.748], [9.392, 2.616], [13.439, 9.811], [4.221, 11.994], [11.362, 1.499], [10.74, 13.786], [15.201, 17.228], [12.665, 4.242], [9.104, 2.067], [19.211, 17.778]], "missing": [[0, 2], [0, 3], [0, 5], [0, 7], [1, 2], [1, 3], [1, 5], [1, 8], [1, 9], [2, 7], [2, 8], [3, 4], [3, 5], [3, 7], [4, 5], [4, 8], [4, 9], [5, 6], [6, 7]]}, {"x": [[10.272, 17.718], [8.359, 1.758], [0.66, 12.83], [1.677, 10.55], [9.189, 11.161], [3.95, 2.233], [7.632, 1.903], [15.406, 7.712], [11.914, 15.212], [12.008, 17.95]], "missing": [[0, 4], [0, 7], [0, 8], [1, 4], [1, 5], [2, 7], [3, 4], [3, 7], [3, 8], [4, 8], [4, 9], [5, 7], [6, 7], [7, 9], [8, 9]]}]  # noqa: E501 (recorded cases)


def _noise_free(case):
    """The case's positions and its exact range matrix, NaN for the missing pairs."""
    x = np.array(case["x"])
    d = np.linalg.norm(x[:, None] - x[None], axis=-1)
    for i, j in case["missing"]:
        d[i, j] = d[j, i] = np.nan
    np.fill_diagonal(d, np.nan)
    return x, d


@pytest.mark.parametrize("case", CASES)
def test_noise_free_missing_pairs_find_the_exact_shape(case):
    x, d = _noise_free(case)
    res = calibrate_anchors(d, range_std_m=0.05)
    assert res.status == "ok" and res.converged
    assert res.cost < 1e-6
    assert aligned_errors(res.positions, x).max() < 1e-4


# Rigid but not globally rigid (a flip fits the same ranges exactly): before the rigidity check
# these came back "ok" and unambiguous in a flipped shape 2.1, 10.9 and 1.8 m off the truth.
FLIPPABLE = [{"x": [[19.852, 13.304], [8.088, 15.974], [3.72, 17.933], [5.16, 13.092], [2.091, 10.048], [19.243, 15.313]], "missing": [[0, 2], [0, 4], [1, 2], [1, 5], [3, 4], [3, 5]]}, {"x": [[9.86, 19.451], [9.628, 1.904], [15.22, 8.734], [12.795, 16.929], [16.654, 13.635], [4.556, 15.424], [17.481, 9.712], [1.465, 0.424], [16.964, 5.489]], "missing": [[0, 2], [0, 4], [0, 6], [0, 7], [0, 8], [1, 5], [1, 6], [1, 7], [2, 3], [2, 4], [2, 5], [3, 4], [3, 6], [3, 7], [3, 8], [5, 8], [6, 7]]}, {"x": [[0.73, 16.367], [1.073, 18.602], [16.298, 7.586], [8.179, 10.916], [19.42, 10.677], [1.282, 12.919], [2.914, 14.543], [13.817, 2.559], [13.963, 7.225]], "missing": [[0, 1], [0, 2], [0, 3], [0, 5], [1, 2], [1, 3], [1, 4], [1, 7], [2, 4], [2, 6], [2, 7], [3, 4], [3, 6], [3, 7], [4, 6], [4, 8], [5, 6], [5, 7], [6, 7]]}]  # noqa: E501


@pytest.mark.parametrize("case", FLIPPABLE)
def test_a_graph_with_a_flip_is_reported_ambiguous(case):
    _, d = _noise_free(case)
    res = calibrate_anchors(d, range_std_m=0.05)
    assert res.cost < 1e-6  # a shape that fits exactly: the truth or its flip
    assert res.ambiguous


@pytest.mark.parametrize("value", [0.0, 3.0])
def test_degenerate_ranges_with_a_pair_missing_give_a_result_or_a_typed_error(value):
    # all anchors coincident (every range 0) or an impossible equilateral set in 2D, one pair
    # missing: the MDS start used to raise numpy's LinAlgError (the shortest-path fill read the
    # zero ranges as missing edges and filled the matrix with inf)
    d = np.full((5, 5), value)
    d[0, 3] = d[3, 0] = np.nan
    try:
        res = calibrate_anchors(d)
    except LocalizationError:
        return
    assert np.isfinite(res.positions).all()


# 3D, 14 anchors, 41 of 91 pairs (globally rigid, but no placement order for the build-up): a
# second shape 3.4 m off fits the noise-free ranges with chi2 7.3 on 5 dof; with 12 random starts
# the solver ended there and reported it "ok". It must find the exact shape, and since the other
# fits within the test's margin, flag the round ambiguous.
NO_PLACEMENT_ORDER_3D = {"x": [[15.666, 1.877, 7.354], [5.475, 15.509, 9.31], [10.363, 2.559, 10.541], [4.351, 8.831, 1.714], [9.088, 19.913, 14.935], [2.144, 16.326, 15.196], [3.491, 6.94, 11.684], [2.377, 1.926, 15.212], [11.28, 0.44, 0.929], [2.526, 16.159, 1.188], [7.613, 5.029, 13.439], [2.381, 10.002, 11.277], [17.986, 0.669, 1.095], [7.172, 15.032, 7.963]], "missing": [[0, 3], [0, 4], [0, 5], [0, 6], [0, 7], [0, 8], [0, 9], [0, 10], [0, 11], [1, 2], [1, 6], [1, 7], [1, 11], [1, 12], [1, 13], [2, 3], [2, 4], [2, 6], [2, 7], [2, 8], [2, 10], [2, 12], [3, 4], [3, 5], [3, 7], [3, 9], [3, 10], [3, 12], [4, 5], [4, 8], [4, 9], [4, 11], [5, 7], [5, 8], [5, 10], [5, 11], [5, 13], [6, 7], [6, 11], [7, 10], [7, 11], [7, 13], [8, 10], [8, 12], [9, 12], [9, 13], [10, 11], [10, 13], [11, 12], [11, 13]]}  # noqa: E501


def test_3d_graph_without_a_placement_order_is_not_a_confident_wrong_shape():
    x, d = _noise_free(NO_PLACEMENT_ORDER_3D)
    res = calibrate_anchors(d, dim=3, range_std_m=0.0587 / 5**0.5)
    assert res.cost < 1e-6 and aligned_errors(res.positions, x).max() < 1e-4
    assert res.ambiguous


# 3D graphs without a placement order (noise-free, globally rigid, 14-15 anchors, 2-6 dof): the
# random starts are the whole search; with 12 (then 48) of them these came back "ok" 24 m and
# 12 m off with fits the noise could explain. The best shape must be confirmed by several starts
# or the round is reported ambiguous; either way never a confident wrong shape.
UNCONFIRMED_3D = [{"x": [[6.0302, 18.3872, 9.8904], [7.1473, 7.431, 3.2009], [9.0459, 0.8871, 15.9813], [15.7609, 8.9912, 15.6127], [6.1488, 14.2568, 18.3117], [1.6701, 13.65, 14.6458], [4.2358, 2.4512, 10.9273], [16.1154, 4.9071, 0.5201], [1.636, 5.0606, 19.9699], [15.0484, 13.0737, 17.5495], [16.9896, 1.9234, 7.0678], [1.24, 1.0657, 1.059], [7.7235, 1.0144, 9.3267], [0.337, 7.6225, 12.7372]], "missing": [[0, 2], [0, 5], [0, 6], [0, 7], [0, 8], [0, 9], [0, 10], [0, 11], [1, 3], [1, 4], [1, 5], [1, 6], [1, 7], [1, 10], [1, 11], [1, 12], [1, 13], [2, 3], [2, 4], [2, 8], [2, 10], [2, 13], [3, 5], [3, 6], [3, 9], [3, 11], [3, 12], [3, 13], [4, 6], [4, 8], [4, 12], [4, 13], [5, 8], [5, 10], [5, 11], [5, 12], [6, 8], [6, 9], [6, 11], [6, 13], [7, 8], [7, 9], [7, 10], [7, 12], [7, 13], [8, 9], [8, 13], [9, 10], [9, 12], [9, 13], [10, 11], [10, 12], [12, 13]]}, {"x": [[13.478, 5.5202, 1.4094], [6.1608, 7.2635, 12.8342], [0.6199, 1.4023, 16.3779], [9.6015, 0.2417, 16.9666], [4.6693, 16.1175, 19.6791], [11.9332, 5.6722, 15.7861], [1.8079, 4.7417, 14.4507], [12.0758, 6.1114, 1.297], [3.6813, 5.0681, 16.9871], [4.8647, 7.3947, 12.0988], [10.6152, 4.078, 17.7348], [18.0405, 16.7397, 4.6943], [12.098, 2.6899, 8.1021], [16.1179, 7.3475, 9.3594], [18.7628, 17.4426, 12.1472]], "missing": [[0, 2], [0, 4], [0, 5], [0, 6], [0, 8], [0, 9], [0, 10], [0, 14], [1, 2], [1, 3], [1, 9], [1, 10], [1, 11], [1, 12], [1, 13], [1, 14], [2, 6], [2, 7], [2, 9], [2, 11], [2, 12], [2, 13], [3, 6], [3, 7], [3, 8], [3, 10], [3, 12], [3, 13], [4, 5], [4, 12], [4, 14], [5, 6], [5, 7], [5, 8], [5, 10], [5, 11], [5, 12], [6, 8], [6, 9], [6, 10], [6, 11], [6, 12], [6, 14], [7, 8], [7, 9], [7, 10], [7, 12], [7, 13], [7, 14], [8, 9], [8, 11], [8, 12], [8, 13], [9, 10], [9, 11], [9, 12], [9, 13], [11, 12], [11, 14], [13, 14]]}]  # noqa: E501


@pytest.mark.parametrize("case", UNCONFIRMED_3D)
def test_3d_random_start_search_never_reports_an_unconfirmed_shape_as_sure(case):
    x, d = _noise_free(case)
    res = calibrate_anchors(d, dim=3, range_std_m=0.0587 / 5**0.5)
    assert res.status == "ok"
    assert res.ambiguous or aligned_errors(res.positions, x).max() < 1e-3
