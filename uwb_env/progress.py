"""Minimal progress reporting on stderr (no extra dependency in the core)."""

from __future__ import annotations

import sys
import time
from collections.abc import Iterable, Iterator
from typing import TypeVar

T = TypeVar("T")


def progress(items: Iterable[T], total: int, label: str, enabled: bool = True) -> Iterator[T]:
    """Yield ``items`` while printing ``label  k/total  elapsed`` at most ~5 times a second."""
    if not enabled:
        yield from items
        return
    start = last = time.perf_counter()
    done = 0
    for item in items:
        yield item
        done += 1
        now = time.perf_counter()
        if now - last > 0.2 or done == total:
            last = now
            sys.stderr.write(f"\r{label}  {done}/{total}  {now - start:5.1f}s")
            sys.stderr.flush()
    sys.stderr.write("\n")
