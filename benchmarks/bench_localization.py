"""Localization accuracy against the Cramér–Rao bound, and solver speed against scipy.

Accuracy: Monte-Carlo RMSE / sqrt(CRLB) for N = 4, 8, 16 anchors (first calibration, paper
frame) and for tags; sigma = 6 cm per range, K = 5 exchanges per ordered pair. Target <= 1.15.
With 10 % of pairs NLOS (a persistent positive bias per pair), plain vs robust (Cauchy)
least squares side by side.

Speed: median time per calibration (N = 4, 8, 16, 32) and per batch of tag fixes, side by side
with a straightforward ``scipy.optimize.least_squares`` implementation of the same problem
(same gauge, same start, same weights, analytic Jacobian) in the same run, and its accuracy.
Target: >= 5x faster at equal accuracy, < 1 ms for 4 anchors.

    python benchmarks/bench_localization.py [--quick]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import interleaved_median_times_s, median_time_s, print_table, write_results  # noqa: E402

from uwb_env.localization import aligned_errors, calibrate_anchors, crlb_anchors, crlb_tags, locate_tags, paper_frame  # noqa: E402
from uwb_env.localization.calibration import _free_mask, trilaterate_initial  # noqa: E402
from uwb_env.localization.models import PairRangeModel  # noqa: E402
from uwb_env.measurements import RangeMatrix  # noqa: E402

SIGMA, K = 0.06, 5


def anchors_layout(n: int, rng: np.random.Generator) -> np.ndarray:
    """n anchors spread over a 20 m square (a ring with jitter: a typical deployment)."""
    ang = 2 * np.pi * np.arange(n) / n
    return 10 + 8 * np.column_stack([np.cos(ang), np.sin(ang)]) + rng.uniform(-1.5, 1.5, (n, 2))


def round_matrix(x, rng, nlos_pairs=0.0):
    n = len(x)
    d = np.linalg.norm(x[:, None] - x[None], axis=-1)
    if nlos_pairs > 0:
        blocked = np.triu(rng.random((n, n)) < nlos_pairs, 1)
        blocked = blocked | blocked.T
        d = d + blocked * (0.3 + rng.exponential(0.5, (n, n)))
    samples = d[None] + SIGMA * rng.standard_normal((K, n, n))
    count = np.full((n, n), K) - K * np.eye(n, dtype=int)
    mean = samples.mean(0)
    np.fill_diagonal(mean, np.nan)
    return RangeMatrix(mean, samples.std(0, ddof=1), count)


def scipy_calibrate(matrix: RangeMatrix, dim: int = 2) -> np.ndarray:
    """Reference: the same gauge-fixed weighted problem solved by scipy.optimize.least_squares."""
    known = RangeMatrix(matrix.mean_m, np.full(matrix.std_m.shape, SIGMA), matrix.count)
    pairs, dist, var = known.symmetric()  # same combination and weights as ours with range_std_m
    n = matrix.n_anchors
    full = np.full((n, n), np.nan)
    full[pairs[:, 0], pairs[:, 1]] = full[pairs[:, 1], pairs[:, 0]] = dist
    np.fill_diagonal(full, 0.0)
    x0 = trilaterate_initial(full, dim)
    free = _free_mask(n, dim, tuple(range(dim + 1)))
    model = PairRangeModel(pairs, n)
    sw = 1.0 / np.sqrt(var)

    def unpack(theta):
        x = np.zeros(n * dim)
        x[free] = theta
        return x.reshape(n, dim)

    sol = least_squares(
        lambda th: (model.evaluate(unpack(th)) - dist) * sw,
        x0.ravel()[free],
        jac=lambda th: model.jacobian(unpack(th))[:, free] * sw[:, None],
    )
    return unpack(sol.x)


def anchor_accuracy(n, trials, rng, nlos=0.0, loss="linear", solver="ours"):
    x = anchors_layout(n, rng)
    rot, trans = paper_frame(x)
    truth = x @ rot.T + trans
    bound = crlb_anchors(x, SIGMA**2 / (2 * K))
    sq = []
    for _ in range(trials):
        m = round_matrix(x, rng, nlos)
        if solver == "ours":
            est = calibrate_anchors(m, range_std_m=SIGMA, loss=loss).positions
        else:
            est = scipy_calibrate(m)
        sq.append(((est - truth) ** 2).sum())
    return float(np.sqrt(np.mean(sq) / np.trace(bound))), float(np.sqrt(np.mean(sq) / n))


def tag_accuracy(trials, rng):
    anchors = anchors_layout(4, rng)
    tags = 10 + rng.uniform(-4, 4, (trials, 2))
    d = np.linalg.norm(tags[:, None] - anchors[None], axis=-1)
    fix = locate_tags(anchors, d + SIGMA * rng.standard_normal(d.shape), SIGMA)
    err2 = ((fix.positions - tags) ** 2).sum(1)
    bound = np.trace(crlb_tags(anchors, tags, SIGMA), axis1=1, axis2=2)
    return float(np.sqrt(err2.mean() / bound.mean()))


def scipy_tags(anchors, ranges):
    out = []
    for r in ranges:
        out.append(least_squares(lambda p, r=r: np.linalg.norm(anchors - p, axis=1) - r, anchors.mean(0)).x)
    return np.array(out)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args(argv)
    trials = 150 if args.quick else 1500
    repeats = 31 if args.quick else 301
    rng = np.random.default_rng(0)
    fig: dict = {}

    rows = []
    for n in (4, 8, 16):
        ratio, rmse = anchor_accuracy(n, trials if n < 16 else trials // 3, rng)
        ratio_sp, _ = anchor_accuracy(n, max(trials // 5, 30), rng, solver="scipy")
        fig[f"rmse_over_crlb_anchors_n{n}"] = ratio
        fig[f"rmse_over_crlb_anchors_n{n}_scipy"] = ratio_sp
        rows.append([f"anchors N={n}", ratio, ratio_sp, rmse])
    fig["rmse_over_crlb_tags"] = tag_accuracy(trials * 10, rng)
    rows.append(["tags (4 anchors)", fig["rmse_over_crlb_tags"], "", ""])
    print_table(f"Accuracy, Gaussian noise sigma={SIGMA} m, K={K} (target RMSE/sqrt(CRLB) <= 1.15)",
                ["case", "ours RMSE/sqrt(CRLB)", "scipy RMSE/sqrt(CRLB)", "ours RMSE per anchor (m)"], rows)

    rows = []
    for n in (8, 16):
        t = trials // 3 if n == 8 else trials // 10
        _, plain = anchor_accuracy(n, t, np.random.default_rng(5), nlos=0.1)
        _, robust = anchor_accuracy(n, t, np.random.default_rng(5), nlos=0.1, loss="cauchy")
        fig[f"nlos10_rmse_m_plain_n{n}"], fig[f"nlos10_rmse_m_robust_n{n}"] = plain, robust
        rows.append([n, plain, robust, plain / robust])
    print_table("10 % NLOS pairs: RMSE per anchor (m), plain vs robust (Cauchy)",
                ["anchors", "plain LS", "robust LS", "plain / robust"], rows)

    rows = []
    for n in (4, 8, 16, 32):
        x = anchors_layout(n, rng)
        m = round_matrix(x, rng)
        reps = repeats if n < 32 else max(5, repeats // 5)
        ours, ref = interleaved_median_times_s(
            [lambda m=m: calibrate_anchors(m, range_std_m=SIGMA), lambda m=m: scipy_calibrate(m)], reps)
        a = calibrate_anchors(m, range_std_m=SIGMA).positions
        b = scipy_calibrate(m)
        fig[f"calibrate_ms_n{n}"] = ours * 1e3
        fig[f"scipy_calibrate_ms_n{n}"] = ref * 1e3
        fig[f"speedup_vs_scipy_n{n}"] = ref / ours
        # frame-free: the reference has no sign rule, so its answer may be the mirror image
        diff = float(aligned_errors(a, b).max())
        fig[f"max_solution_difference_m_n{n}"] = diff
        rows.append([n, ours * 1e3, ref * 1e3, ref / ours, diff])
    anchors = anchors_layout(4, rng)
    tags = 10 + rng.uniform(-4, 4, (64, 2))
    ranges = np.linalg.norm(tags[:, None] - anchors[None], axis=-1) + SIGMA * rng.standard_normal((64, 4))
    ours = median_time_s(lambda: locate_tags(anchors, ranges, SIGMA), repeats)
    ref = median_time_s(lambda: scipy_tags(anchors, ranges), max(5, repeats // 10))
    diff = float(np.abs(locate_tags(anchors, ranges, SIGMA).positions - scipy_tags(anchors, ranges)).max())
    fig.update(tag_batch64_ms=ours * 1e3, scipy_tag_batch64_ms=ref * 1e3, speedup_vs_scipy_tags=ref / ours)
    rows.append(["64 tags", ours * 1e3, ref * 1e3, ref / ours, diff])
    print_table("Speed: median ms per solve, ours vs scipy.optimize.least_squares (same problem)",
                ["problem", "ours (ms)", "scipy (ms)", "speedup", "max |ours - scipy| aligned (m)"], rows)
    write_results("bench_localization", fig, args.quick)
    return fig


if __name__ == "__main__":
    main()
