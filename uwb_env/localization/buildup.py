"""Build-up starts: anchors placed one at a time from their ranges, branching over mirror choices.

With pairs missing, every start that embeds the whole matrix at once (MDS on shortest-path
filled ranges, SMACOF from random shapes) can land in a fold: an anchor with few links mirrored
across the line (plane) through its neighbours, a basin whose cost is 10-1000x the truth's.
Placing anchors in turn instead (a triangle first, then each anchor from its ranges to anchors
already placed) makes the folds a discrete choice per anchor: the two intersections of its
circles (spheres), each refined on all its ranges to placed anchors. Keeping the ``beam``
partial shapes of lowest weighted misfit over those choices searches the folds one anchor at a
time (a beam search over sequential trilateration), instead of hoping that a random start
lands in the right basin. Noise-free, with a placement order (each anchor after the seed has
>= dim links to earlier ones) and a wide enough beam, the true shape is among the results.

The results are starts for the least-squares solver, not solutions.
"""

from __future__ import annotations

import numpy as np
from numba import njit
from scipy.special import chdtri

from uwb_env.localization._lm_kernel import LOSS_CODES, _weight
from uwb_env.localization.robust import robust_cost

SEED_TRIANGLES = 3
BEAM = 8
KEEP = 4  # starts handed on per seed: the lowest final misfits
# Placements whose misfits tie with the best (within the fit test's one-dof chi-square margin at
# 1e-3) all stay, up to these caps: noise-free, every mirror choice of an anchor with exactly dim
# links costs 0, and a stable sort would keep an arbitrary ``beam`` of them.
TIE_CHI2 = float(chdtri(1, 1e-3))
MAX_BEAM, MAX_KEEP = 32, 12
REFINE_ITERATIONS = 6


def buildup_starts(full: np.ndarray, weight: np.ndarray, dim: int, tol_m: float,
                   beam: int = BEAM, seeds: int = SEED_TRIANGLES, keep: int = KEEP, robust_c=None) -> list[np.ndarray]:
    """Up to ``seeds * keep`` (n, dim) starts, the lowest-misfit placements of each seed.

    full: (n, n) ranges, NaN where a pair is missing (diagonal 0); weight: (n, n) inverse
    variances (0 where missing); tol_m: shapes closer than this (max coordinate difference)
    count as one. Seeds without a placement order give no start (the other starts remain).
    robust_c (2D): ranges measured longer than a placement says are NLOS candidates: each
    anchor is placed from every pair of its first five neighbours (not only the best-spread
    pair, which one biased range would spoil) and refined and ranked with those ranges
    down-weighted (one-sided Cauchy, scale robust_c in standard deviations).
    """
    n = full.shape[0]
    linked = np.isfinite(full)
    np.fill_diagonal(linked, False)
    starts = []
    for seed in _seed_triangles(full, linked, seeds):
        order = _placement_order(linked, seed, dim)
        if order is None:
            continue
        x = np.full((1, n, dim), np.nan)
        x[0, list(seed)] = _place_triangle(full, seed, dim)
        cost = np.zeros(1)
        placed = list(seed)
        for k in order:
            nb = [j for j in placed if linked[k, j]]
            x, cost = _extend(x, cost, full[k, nb], weight[k, nb], nb, k, dim, robust_c)
            placed.append(k)
            x, cost = _prune(x, cost, placed, _with_ties(cost, beam, MAX_BEAM), tol_m)
            if len(x) == 0:  # every placement non-finite (degenerate ranges): no start from this seed
                break
        best = np.argsort(cost, kind="stable")[:_with_ties(cost, keep, MAX_KEEP)]
        starts.extend(x[i] for i in best if np.isfinite(x[i]).all())
    return starts


def _seed_triangles(full, linked, count):
    """The ``count`` fully linked triangles whose smallest altitude (from the ranges) is largest:
    the best-conditioned frames to place the others from."""
    # (i, j, k) with i < j < k, every pair linked
    upper = np.triu(linked, 1)
    i, j, k = np.nonzero(upper[:, :, None] & upper[:, None, :] & upper[None, :, :])
    if len(i) == 0:
        return []
    a, b, c = full[i, j], full[j, k], full[i, k]
    s = 0.5 * (a + b + c)
    area = np.sqrt(np.maximum(s * (s - a) * (s - b) * (s - c), 0.0))
    altitude = 2.0 * area / np.maximum(np.maximum(a, b), np.maximum(c, 1e-300))
    best = np.argsort(-altitude, kind="stable")[:count]
    return [(int(i[t]), int(j[t]), int(k[t])) for t in best if altitude[t] > 0]


def _placement_order(linked, seed, dim):
    """Greedy order: next the unplaced anchor with the most links to placed ones (>= dim);
    None when some anchor never gets dim links (no sequential placement from this seed)."""
    n = linked.shape[0]
    placed = np.zeros(n, dtype=bool)
    placed[list(seed)] = True
    order = []
    while not placed.all():
        links = np.where(placed, -1, linked[:, placed].sum(1))
        k = int(np.argmax(links))
        if links[k] < dim:
            return None
        order.append(k)
        placed[k] = True
    return order


def _place_triangle(full, seed, dim):
    i, j, k = seed
    d_ij, d_ik, d_jk = full[i, j], full[i, k], full[j, k]
    xk = (d_ik**2 - d_jk**2 + d_ij**2) / (2.0 * d_ij)
    yk = np.sqrt(max(d_ik**2 - xk**2, 0.0))
    pts = np.zeros((3, dim))
    pts[1, 0] = d_ij
    pts[2, 0], pts[2, 1] = xk, yk
    return pts


def _extend(x, cost, ranges, weight, nb, k, dim, robust_c=None):
    """Both mirror placements of anchor k in every state (from each base pair of neighbours),
    refined on its ranges to ``nb``; the states' misfits grow by the placement's."""
    ref = x[:, nb]  # (S, m, dim)
    s = x.shape[0]
    if robust_c is None or len(nb) <= dim or dim != 2:
        bases = [_spread_pair(ref[0])]
    else:
        m = min(len(nb), 5)
        bases = [(a, b) for a in range(m) for b in range(a + 1, m)]
    cands = np.concatenate([_intersections(ref, ranges, dim, base) for base in bases], axis=1)  # (S, 2B, dim)
    loss, c_scale = ("linear", 1.0) if robust_c is None else ("nlos", robust_c)
    c = cands.shape[1]
    ref2 = np.repeat(ref, c, axis=0)
    p = cands.reshape(c * s, dim)
    if len(nb) > dim:
        p = _refine(p, ref2, ranges, weight, LOSS_CODES[loss], c_scale)
    # whitened residuals model - measured: < 0 is a range measured longer (an NLOS candidate)
    z = (np.linalg.norm(ref2 - p[:, None], axis=-1) - ranges) * np.sqrt(weight)
    new_cost = np.repeat(cost, c) + 2.0 * robust_cost(z, loss, c_scale, axis=-1)  # chi-square units
    new_x = np.repeat(x, c, axis=0)
    new_x[:, k] = p
    return new_x, new_cost


def _intersections(ref, ranges, dim, base):
    """Per state, the two points at the measured ranges from the neighbours ``base`` (and in
    3D a third, off their line): mirror images across their line (plane). Circles that miss each
    other (noise) give their closest approach twice."""
    a, b = base
    if dim == 2:
        pa, pb = ref[:, a], ref[:, b]
        d = np.linalg.norm(pb - pa, axis=1)
        d = np.maximum(d, 1e-300)
        u = (pb - pa) / d[:, None]
        along = (ranges[a] ** 2 - ranges[b] ** 2 + d * d) / (2.0 * d)
        h = np.sqrt(np.maximum(ranges[a] ** 2 - along**2, 0.0))
        perp = np.column_stack([-u[:, 1], u[:, 0]])
        mid = pa + along[:, None] * u
        return np.stack([mid + h[:, None] * perp, mid - h[:, None] * perp], axis=1)
    c = _third_reference(ref[0], a, b)
    pa, pb, pc = ref[:, a], ref[:, b], ref[:, c]
    ex = pb - pa
    d = np.maximum(np.linalg.norm(ex, axis=1), 1e-300)
    ex = ex / d[:, None]
    i = ((pc - pa) * ex).sum(1)
    ey = pc - pa - i[:, None] * ex
    j = np.maximum(np.linalg.norm(ey, axis=1), 1e-300)
    ey = ey / j[:, None]
    ez = np.cross(ex, ey)
    ra, rb, rc = ranges[a], ranges[b], ranges[c]
    px = (ra**2 - rb**2 + d * d) / (2.0 * d)
    py = (ra**2 - rc**2 + i * i + j * j) / (2.0 * j) - i / j * px
    pz = np.sqrt(np.maximum(ra**2 - px**2 - py**2, 0.0))
    base = pa + px[:, None] * ex + py[:, None] * ey
    return np.stack([base + pz[:, None] * ez, base - pz[:, None] * ez], axis=1)


def _spread_pair(pts):
    """The two neighbours farthest apart (the best-conditioned intersection base)."""
    d = np.linalg.norm(pts[:, None] - pts[None], axis=-1)
    a, b = np.unravel_index(int(np.argmax(d)), d.shape)
    return int(a), int(b)


def _third_reference(pts, a, b):
    """The neighbour farthest from the line through a and b (3D: the plane's third point)."""
    u = pts[b] - pts[a]
    u = u / max(np.linalg.norm(u), 1e-300)
    off = pts - pts[a]
    off = off - (off @ u)[:, None] * u
    dist = np.linalg.norm(off, axis=1)
    dist[[a, b]] = -1.0
    return int(np.argmax(dist))


@njit(cache=True)
def _refine(p, ref, ranges, weight, code, c):
    """A few weighted Gauss-Newton steps of each point on its ranges (all states at once), each
    range's weight times the IRLS weight of loss ``code`` (``_lm_kernel.LOSS_CODES``, scale c);
    a singular normal matrix leaves the point where it is."""
    s_count, m, dim = ref.shape
    p = p.copy()
    for s in range(s_count):
        for _ in range(REFINE_ITERATIONS if code == 0 else 3 * REFINE_ITERATIONS):
            h = np.zeros((dim, dim))
            g = np.zeros(dim)
            for j in range(m):
                d2 = 0.0
                for a in range(dim):
                    d2 += (p[s, a] - ref[s, j, a]) ** 2
                dist = max(np.sqrt(d2), 1e-12)
                r = dist - ranges[j]
                w = weight[j] * _weight(r * np.sqrt(weight[j]), code, c)
                for a in range(dim):
                    ja = (p[s, a] - ref[s, j, a]) / dist
                    g[a] += w * ja * r
                    for b in range(dim):
                        h[a, b] += w * ja * (p[s, b] - ref[s, j, b]) / dist
            if abs(np.linalg.det(h)) <= 1e-12 * max(h[0, 0], 1e-300) ** dim:
                break
            p[s] -= np.linalg.solve(h, g)
    return p


def _with_ties(cost, count, cap):
    """``count``, or more (up to ``cap``) when more states tie with the lowest misfit."""
    finite = cost[np.isfinite(cost)]
    if len(finite) == 0:
        return count
    return max(count, min(cap, int((finite <= finite.min() + TIE_CHI2).sum())))


def _prune(x, cost, placed, beam, tol_m):
    """The ``beam`` lowest-misfit states, one per shape (a state within tol_m of a kept one is
    a duplicate: robust placements from many neighbour pairs collapse onto few points, so the
    duplicates are dropped before the beam is cut, over every finite state)."""
    order = np.argsort(cost, kind="stable")
    order = order[np.isfinite(cost[order])]
    if len(order) == 0:
        return x[:0], cost[:0]
    pts = np.ascontiguousarray(x[order][:, placed])
    kept = order[_distinct_prefix(pts, beam, tol_m)]
    return x[kept], cost[kept]


@njit(cache=True)
def _distinct_prefix(pts, beam, tol_m):
    """Indices of the first ``beam`` states (in order) that differ from every earlier kept one
    by more than tol_m in some coordinate."""
    kept = np.empty(min(beam, pts.shape[0]), dtype=np.int64)
    count = 0
    for i in range(pts.shape[0]):
        duplicate = False
        for k in range(count):
            j = kept[k]
            far = False
            for a in range(pts.shape[1]):
                for b in range(pts.shape[2]):
                    if abs(pts[i, a, b] - pts[j, a, b]) > tol_m:
                        far = True
                        break
                if far:
                    break
            if not far:
                duplicate = True
                break
        if not duplicate:
            kept[count] = i
            count += 1
            if count == len(kept):
                break
    return kept[:count]
