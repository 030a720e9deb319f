"""Shared helpers for the benchmark scripts: timing, tables, result files."""

from __future__ import annotations

import datetime as _dt
import json
import os
import platform
import time
from collections.abc import Callable
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"


def machine() -> str:
    return f"{platform.node()} {platform.machine()} {os.cpu_count()} cpu, Python {platform.python_version()}"


def rate(fn: Callable[[], object], min_time_s: float, batch: int = 100) -> float:
    """Calls per second of ``fn``, running batches until ``min_time_s`` has passed."""
    calls, start = 0, time.perf_counter()
    while True:
        for _ in range(batch):
            fn()
        calls += batch
        elapsed = time.perf_counter() - start
        if elapsed >= min_time_s:
            return calls / elapsed


def median_time_s(fn: Callable[[], object], repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    times.sort()
    return times[len(times) // 2]


def interleaved_median_times_s(fns: list[Callable[[], object]], repeats: int, block: int = 10) -> list[float]:
    """Median seconds per call of each of ``fns``, timed in alternating blocks of ``block``
    calls: drifts in machine speed hit all of them alike (a fair side-by-side ratio on a noisy
    VM), while each function still runs warm, as it would in a loop of its own."""
    times: list[list[float]] = [[] for _ in fns]
    for _ in range(max(1, repeats // block)):
        for fn, out in zip(fns, times, strict=True):
            for _ in range(block):
                t = time.perf_counter()
                fn()
                out.append(time.perf_counter() - t)
    return [sorted(t)[len(t) // 2] for t in times]


def alternating_rates(steppers: list[Callable[[], object]], seconds: float, rounds: int) -> list[float]:
    """Best calls/s of each stepper over ``rounds`` alternating timed blocks. Alternating makes
    a slow phase of this shared VM hit every stepper alike; the best block is timeit's
    convention (slower blocks measure interference, not the code)."""
    out: list[list[float]] = [[] for _ in steppers]
    for _ in range(rounds):
        for fn, rates in zip(steppers, out, strict=True):
            rates.append(rate(fn, seconds / rounds, batch=200))
    return [max(r) for r in out]


def print_table(title: str, header: list[str], rows: list[list[object]]) -> None:
    cells = [[str(c) for c in header]] + [[f"{c:.4g}" if isinstance(c, float) else str(c) for c in r] for r in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(header))]
    print(f"\n{title}")
    for k, r in enumerate(cells):
        print("  ".join(c.rjust(w) for c, w in zip(r, widths, strict=True)))
        if k == 0:
            print("  ".join("-" * w for w in widths))


def write_results(name: str, figures: dict, quick: bool) -> Path:
    """Write a flat JSON object (figures + date + machine) to benchmarks/results/<name>.json."""
    flat = {k: v for k, v in figures.items() if not isinstance(v, (dict, list))}
    flat.update(date=_dt.datetime.now().isoformat(timespec="seconds"), machine=machine(), quick=quick)
    RESULTS.mkdir(exist_ok=True)
    path = RESULTS / f"{name}.json"
    path.write_text(json.dumps(flat, indent=2, sort_keys=True) + "\n")
    print(f"\nwrote {path}")
    return path
