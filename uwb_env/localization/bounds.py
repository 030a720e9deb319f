"""Cramér–Rao lower bounds for range-only positioning.

Tag: J = sum_i u_i u_i^T / sigma_i^2 (Fisher information of the tag position), CRLB = J^-1.

Anchor self-calibration: the Fisher information of all anchor coordinates from pairwise
ranges is singular (translation, rotation, reflection are unobservable). Two bounds:

- ``gauge="paper"``: the paper's frame convention (anchor 0 at the origin, anchor 1 on +x,
  in 3D the anchor farthest off that axis in the xy-plane): the information restricted to the free coordinates,
  inverted, zeros on the fixed ones. This is what the calibration solver's covariance
  estimates.
- ``gauge="free"``: the Moore–Penrose pseudo-inverse, the bound for frame-independent error
  (after the best rigid alignment).
"""

from __future__ import annotations

import numpy as np

from uwb_env.localization.models import PairRangeModel, TagRangeModel


def crlb_tags(anchors: np.ndarray, tags: np.ndarray, range_std_m: float | np.ndarray) -> np.ndarray:
    """(T, dim, dim) CRLB of each tag's position; ``range_std_m`` scalar or (T, N)."""
    tags = np.atleast_2d(np.asarray(tags, dtype=float))
    u = TagRangeModel(anchors).jacobian(tags)
    iv = np.broadcast_to(1.0 / np.asarray(range_std_m, dtype=float) ** 2, u.shape[:2])
    info = np.einsum("tai,ta,taj->tij", u, iv, u)
    return np.linalg.inv(info)


def anchor_fisher_information(
    positions: np.ndarray, range_var_m2: float | np.ndarray, pairs: np.ndarray | None = None
) -> np.ndarray:
    """(n*dim, n*dim) Fisher information of all anchor coordinates from pairwise ranges."""
    n = len(positions)
    if pairs is None:
        pairs = np.column_stack(np.triu_indices(n, 1))
    jac = PairRangeModel(pairs, n).jacobian(np.asarray(positions, dtype=float))
    iv = np.broadcast_to(1.0 / np.asarray(range_var_m2, dtype=float), (len(pairs),))
    return (jac * iv[:, None]).T @ jac


def crlb_anchors(
    positions: np.ndarray,
    range_var_m2: float | np.ndarray,
    pairs: np.ndarray | None = None,
    gauge: str = "paper",
    refs: tuple[int, ...] | None = None,
) -> np.ndarray:
    """(n*dim, n*dim) CRLB of the anchor coordinates under ``gauge`` ("paper" or "free").

    Args:
        positions: (n, dim) true anchor positions (any frame: the bound is invariant).
        range_var_m2: variance of each pair's range (scalar or per pair).
        pairs: (P, 2) measured pairs; default all.
        refs: gauge anchors for ``paper`` (default: 0, 1 and in 3D the anchor farthest off
            the 0-1 axis, as the solver chooses).
    """
    positions = np.asarray(positions, dtype=float)
    n, dim = positions.shape
    info = anchor_fisher_information(positions, range_var_m2, pairs)
    if gauge == "free":
        return np.linalg.pinv(info, rcond=1e-10, hermitian=True)
    if gauge != "paper":
        raise ValueError(f"gauge={gauge!r}: must be 'paper' or 'free'")
    from uwb_env.localization.alignment import frame_refs, paper_frame
    from uwb_env.localization.calibration import _free_mask

    refs = frame_refs(positions) if refs is None else refs
    # Information is frame-dependent only through rotation: express it in the paper frame.
    rot, _ = paper_frame(positions, refs)
    big = np.kron(np.eye(n), rot)
    info_frame = big @ info @ big.T
    free = _free_mask(n, dim, refs)
    bound = np.zeros_like(info)
    bound[np.ix_(free, free)] = np.linalg.inv(info_frame[np.ix_(free, free)])
    return bound


def gauge_nees(positions: np.ndarray, covariance: np.ndarray, refs: tuple[int, ...],
               truth: np.ndarray) -> tuple[float, np.ndarray]:
    """Normalized estimation error squared of a calibration in its own gauge: estimate and truth
    both in the paper frame of the gauge anchors ``refs`` (the estimate's frame handedness for
    the truth too: near-degenerate layouts can flip the sign convention), the (N dim, N dim)
    ``covariance`` rotated with the estimate. Returns (NEES, (N, dim) error); an honest
    covariance gives a chi-square NEES with N dim - dim (dim + 1) / 2 degrees of freedom."""
    from uwb_env.localization.alignment import paper_frame

    n, dim = positions.shape
    rot, trans = paper_frame(positions, refs)
    est = positions @ rot.T + trans
    blocks = np.kron(np.eye(n), rot)
    cov = blocks @ covariance @ blocks.T
    rot_t, trans_t = paper_frame(truth, refs)
    true = truth @ rot_t.T + trans_t
    if float(est[:, -1] @ true[:, -1]) < 0.0:
        true = true * np.r_[np.ones(dim - 1), -1.0]
    err = est - true
    e = err.ravel()
    return float(e @ np.linalg.pinv(cov, rcond=1e-12, hermitian=True) @ e), err
