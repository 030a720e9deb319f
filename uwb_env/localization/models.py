"""Range measurement models with analytic Jacobians (navlie style).

Each model has ``evaluate(x)`` (predicted ranges), ``jacobian(x)`` (analytic) and
``jacobian_fd(x)`` (central finite differences, for tests).
"""

from __future__ import annotations

import numpy as np


def _jacobian_fd(evaluate, x: np.ndarray, step: float = 1e-6) -> np.ndarray:
    x = np.asarray(x, dtype=float)
    flat = x.ravel()
    cols = []
    for k in range(flat.size):
        dx = np.zeros_like(flat)
        dx[k] = step
        cols.append((evaluate((flat + dx).reshape(x.shape)) - evaluate((flat - dx).reshape(x.shape))) / (2 * step))
    return np.stack(cols, axis=-1)


class PairRangeModel:
    """Inter-anchor ranges: h_p(X) = ||X[i_p] - X[j_p]|| for pairs p = (i_p, j_p).

    The state ``X`` is (n_anchors, dim); the Jacobian is (P, n_anchors * dim), row p holding
    u_p^T at anchor i_p and -u_p^T at anchor j_p, u_p the unit vector from j_p to i_p.
    """

    def __init__(self, pairs: np.ndarray, n_anchors: int):
        self.pairs = np.asarray(pairs, dtype=int).reshape(-1, 2)
        self.n_anchors = n_anchors
        self._rows = np.arange(len(self.pairs))

    def evaluate(self, x: np.ndarray) -> np.ndarray:
        diff = x[self.pairs[:, 0]] - x[self.pairs[:, 1]]
        return np.sqrt((diff * diff).sum(axis=1))

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        diff = x[self.pairs[:, 0]] - x[self.pairs[:, 1]]
        dist = np.sqrt((diff * diff).sum(axis=1))
        u = diff / np.maximum(dist, 1e-12)[:, None]
        jac = np.zeros((len(self.pairs), self.n_anchors, x.shape[1]))
        jac[self._rows, self.pairs[:, 0]] = u
        jac[self._rows, self.pairs[:, 1]] = -u
        return jac.reshape(len(self.pairs), -1)

    def jacobian_fd(self, x: np.ndarray) -> np.ndarray:
        return _jacobian_fd(self.evaluate, x).reshape(len(self.pairs), -1)


class TagRangeModel:
    """Tag-to-anchor ranges for many tags at once: h_{t,a}(P) = ||P[t] - A[a]||.

    The state ``P`` is (n_tags, dim); ``jacobian`` returns (n_tags, n_anchors, dim): each tag's
    ranges depend only on its own position (block-diagonal), rows are unit vectors from the
    anchor to the tag.
    """

    def __init__(self, anchors: np.ndarray):
        self.anchors = np.asarray(anchors, dtype=float)

    def evaluate(self, p: np.ndarray) -> np.ndarray:
        diff = p[:, None, :] - self.anchors[None, :, :]
        return np.sqrt((diff * diff).sum(axis=-1))

    def jacobian(self, p: np.ndarray) -> np.ndarray:
        diff = p[:, None, :] - self.anchors[None, :, :]
        dist = np.sqrt((diff * diff).sum(axis=-1))
        return diff / np.maximum(dist, 1e-12)[..., None]

    def jacobian_fd(self, p: np.ndarray) -> np.ndarray:
        full = _jacobian_fd(self.evaluate, p)  # (T, A, T*dim)
        t, dim = p.shape
        full = full.reshape(t, self.anchors.shape[0], t, dim)
        return full[np.arange(t), :, np.arange(t), :]
