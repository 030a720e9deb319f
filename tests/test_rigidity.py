"""Generic global rigidity (Gortler-Healy-Thurston stress test) on graphs whose answer is known,
and the build-up starts that place anchors one at a time over each one's mirror choice."""

import itertools

import numpy as np
import pytest

from uwb_env.localization import aligned_errors
from uwb_env.localization.buildup import buildup_starts
from uwb_env.localization.rigidity import generically_globally_rigid


def complete(n):
    return np.array(list(itertools.combinations(range(n), 2)))


WHEEL5 = [(5, k) for k in range(5)] + [(k, (k + 1) % 5) for k in range(5)]
K33 = [(a, b) for a in range(3) for b in range(3, 6)]


@pytest.mark.parametrize("pairs, n, dim, expected", [
    (complete(3), 3, 2, True),
    (complete(3)[1:], 3, 2, False),  # a path: flexible
    (complete(4), 4, 2, True),
    (complete(4)[1:], 4, 2, False),  # quadrilateral with one diagonal: folds across it
    (WHEEL5, 6, 2, True),  # 3-connected and redundantly rigid
    (K33, 6, 2, False),  # minimally rigid: a flip exists
    (complete(5), 5, 3, True),
    (complete(5)[1:], 5, 3, False),
    (complete(12), 12, 2, True),
])
def test_known_graphs(pairs, n, dim, expected):
    assert generically_globally_rigid(np.array(pairs), n, dim) is expected


def test_an_anchor_with_dim_links_makes_the_graph_flippable():
    pairs = [p for p in complete(7) if 6 not in p] + [(0, 6), (1, 6)]
    assert not generically_globally_rigid(np.array(pairs), 7, 2)
    assert generically_globally_rigid(np.array(pairs + [(2, 6)]), 7, 2)


def sparse_case(n, dim, frac, seed):
    rng = np.random.default_rng(seed)
    while True:
        x = rng.uniform(0, 20, (n, dim))
        full = np.linalg.norm(x[:, None] - x[None], axis=-1)
        drop = np.triu(rng.random((n, n)) < frac, 1)
        full[drop | drop.T] = np.nan
        if (np.isfinite(full).sum(1) - 1 >= dim + 1).all():
            return x, full


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("seed", range(5))
def test_noise_free_buildup_contains_the_true_shape(dim, seed):
    x, full = sparse_case(10, dim, 0.3, seed)
    weight = np.where(np.isfinite(full), 1.0, 0.0)
    starts = buildup_starts(full, weight, dim, tol_m=1e-6)
    assert starts, "a 30 %-sparse 10-anchor graph has a placement order"
    # every start comes back as a full shape; one of them is the truth up to a rigid motion
    assert all(s.shape == (10, dim) and np.isfinite(s).all() for s in starts)
    assert min(aligned_errors(s, x).max() for s in starts) < 1e-6


def test_buildup_without_a_triangle_gives_no_start():
    # a 4-cycle: no three anchors all linked, nothing to seed the placement from
    full = np.full((4, 4), np.nan)
    for i in range(4):
        full[i, (i + 1) % 4] = full[(i + 1) % 4, i] = 5.0
    np.fill_diagonal(full, 0.0)
    assert buildup_starts(full, np.where(np.isfinite(full), 1.0, 0.0), 2, tol_m=1e-6) == []


def test_repeated_and_self_pairs_do_not_change_the_answer_and_bad_indices_are_errors():
    flippable = complete(4)[1:]  # K4 minus an edge
    noisy = np.vstack([flippable, flippable[:2], [[2, 2]], flippable[:, ::-1]])
    for seed in range(20):  # a repeated pair used to add a spurious stress for some seeds
        assert not generically_globally_rigid(noisy, 4, 2, seed=seed)
    with pytest.raises(ValueError, match="anchor indices"):
        generically_globally_rigid(np.array([[0, 1], [1, -1]]), 4, 2)
    with pytest.raises(ValueError, match="anchor indices"):
        generically_globally_rigid(np.array([[0, 5]]), 3, 2)
