"""Minimal progress reporting on stderr (no extra dependency in the core).

On a terminal one line updates in place (``\\r``); in a log (stderr not a TTY) each update is
its own line, at most every ``log_every_s`` seconds, so lines never run together.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Iterable, Iterator
from typing import TypeVar

T = TypeVar("T")


def _clock(seconds: float) -> str:
    seconds = int(round(seconds))
    return f"{seconds // 60}:{seconds % 60:02d}"


def format_progress(label: str, done: int, total: int, elapsed_s: float) -> str:
    """``label  k/total (p%)  elapsed m:ss  ETA m:ss`` (ETA from the mean rate so far)."""
    pct = 100.0 * done / total if total else 100.0
    eta = "?" if done == 0 else _clock(elapsed_s / done * (total - done))
    return f"{label}  {done}/{total} ({pct:3.0f}%)  elapsed {_clock(elapsed_s)}  ETA {eta}"


def progress(items: Iterable[T], total: int, label: str, enabled: bool = True, stream=None,
             log_every_s: float = 10.0) -> Iterator[T]:
    """Yield ``items`` while reporting progress with elapsed time and ETA; the 0/total line is
    written at once, so a long first item does not look like a hang."""
    if not enabled:
        yield from items
        return
    stream = stream or sys.stderr
    tty = hasattr(stream, "isatty") and stream.isatty()
    every = 0.2 if tty else log_every_s

    def show(done: int, now: float) -> None:
        text = format_progress(label, done, total, now - start)
        stream.write(f"\r{text}" if tty else f"{text}\n")
        stream.flush()

    start = last = time.perf_counter()
    done = 0
    show(0, start)
    for item in items:
        yield item
        done += 1
        now = time.perf_counter()
        if now - last > every or done == total:
            last = now
            show(done, now)
    if tty:
        stream.write("\n")
