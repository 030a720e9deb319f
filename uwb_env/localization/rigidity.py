"""Whether a pair graph determines a unique shape: generic global rigidity.

A rigid graph can still have several shapes with the same ranges: a quadrilateral with one
diagonal folds across it, an anchor linked to only two others (2D) mirrors across their line.
Noise-free, both shapes fit exactly, so no solver can tell them apart and a fit reported without
that caveat is a coin toss reported as a position. Gortler, Healy and Thurston (2010,
"Characterizing generic global rigidity", Amer. J. Math. 132) showed a graph on n >= d + 2
vertices is globally rigid in R^d for generic positions iff it has an equilibrium stress whose
stress matrix has rank n - d - 1, a test that one random generic configuration decides with
probability 1 (their randomized algorithm). Used for first calibrations with missing pairs.
"""

from __future__ import annotations

import numpy as np


def _unordered_pairs(pairs: np.ndarray) -> np.ndarray:
    """One row per unordered pair, self-pairs dropped (a repeated pair would add a spurious stress)."""
    pairs = np.asarray(pairs, dtype=int).reshape(-1, 2)
    return np.unique(np.sort(pairs[pairs[:, 0] != pairs[:, 1]], axis=1), axis=0)


def _rigidity_matrix(pairs: np.ndarray, p: np.ndarray) -> np.ndarray:
    """(m, n*dim) rigidity matrix of unordered ``pairs`` at positions ``p`` (n, dim)."""
    n, dim = p.shape
    i, j = pairs[:, 0], pairs[:, 1]
    edge = p[i] - p[j]
    rows = np.arange(len(pairs))
    rigidity = np.zeros((len(pairs), n, dim))
    rigidity[rows, i] = edge
    rigidity[rows, j] = -edge
    return rigidity.reshape(len(pairs), n * dim)


def generically_rigid(pairs: np.ndarray, n: int, dim: int, seed: int = 0) -> bool:
    """True when the graph is (infinitesimally) rigid in ``dim`` dimensions for generic anchor
    positions: the rigidity matrix at random positions has rank n*dim - dim(dim+1)/2 (for
    n <= dim + 1: every pair measured). A flexible graph's shapes form a continuum."""
    pairs = _unordered_pairs(pairs)
    if n <= dim + 1:
        return len(pairs) == n * (n - 1) // 2
    rigidity = _rigidity_matrix(pairs, np.random.default_rng(seed).standard_normal((n, dim)))
    return bool(np.linalg.matrix_rank(rigidity, tol=1e-9) == n * dim - dim * (dim + 1) // 2)


def generically_globally_rigid(pairs: np.ndarray, n: int, dim: int, seed: int = 0) -> bool:
    """True when the graph (``pairs``: (m, 2) anchor indices) has one realization in ``dim``
    dimensions up to rotation, translation and reflection, for generic anchor positions."""
    pairs = np.asarray(pairs, dtype=int).reshape(-1, 2)
    if len(pairs) and (pairs.min() < 0 or pairs.max() >= n):
        raise ValueError(f"pairs: anchor indices must lie in [0, {n}), got {pairs.min()}..{pairs.max()}")
    pairs = _unordered_pairs(pairs)
    if n <= dim + 1:  # a simplex: unique iff every pair is measured
        return len(pairs) == n * (n - 1) // 2
    rng = np.random.default_rng(seed)
    p = rng.standard_normal((n, dim))
    rigidity = _rigidity_matrix(pairs, p)
    # a random equilibrium stress: a random vector's residual off the rigidity matrix's column
    # space (the left null space), generic in the stress space with probability 1
    v = rng.standard_normal(len(pairs))
    coef, _, rank, _ = np.linalg.lstsq(rigidity, v, rcond=1e-9)
    if rank < n * dim - dim * (dim + 1) // 2:
        return False  # flexible: not even locally rigid
    w = v - rigidity @ coef
    if np.linalg.norm(w) <= 1e-9 * np.linalg.norm(v):
        return False  # no stress (minimally rigid): every such graph (n >= d + 2) has a flip
    omega = np.zeros((n, n))
    i, j = pairs[:, 0], pairs[:, 1]
    np.add.at(omega, (i, j), -w)
    np.add.at(omega, (j, i), -w)
    np.add.at(omega, (i, i), w)
    np.add.at(omega, (j, j), w)
    ev = np.abs(np.linalg.eigvalsh(omega))
    # threshold relative to the stress's own size (the eigenvalues scale with it)
    return int((ev > 1e-8 * max(ev.max(), np.linalg.norm(w))).sum()) == n - dim - 1
