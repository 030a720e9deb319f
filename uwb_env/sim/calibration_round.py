"""Timing and measurement of one calibration round.

The round of the reference firmware (``TIERS/dwm1001-uwb-firmware``,
``Autocalibration/*/ss_init_main.c``): every anchor is initiator in turn (index order); each
initiator polls the others "in counter-clockwise order" (i-1, i-2, ... mod n) until K SS-TWR
exchanges have been answered, then broadcasts that pair's mean and std in an ``F`` frame and
waits out its RX timeout (66.7 ms; the frame expects an answer that never comes) before the
next pair; the last pair's ``F`` hands the initiator role on. So the idle time is spent once
per *pair*: a round of n anchors is n (n - 1) pair slots of ``pair_idle_s + K exchange_s``.
Robots keep moving, so each exchange ranges the positions at its own timestamp.

Simplification: the simulator makes K attempts per pair and a lost one is missing from the
pair's count, where the firmware retries until K answers (each failed poll another RX
timeout). The fitted constants are the measured rounds' averages, retries included.

A *per-anchor* round is one initiator's block of that schedule alone (``initiators=[i]``): the
anchor re-locates against the others, at 1/n of a team round's channel time ((n - 1) pair
slots), with the same fitted constants.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from uwb_env.config import CalibrationConfig
from uwb_env.measurements import RangeMatrix
from uwb_env.sim.ranging import RangeModel


@dataclass(frozen=True)
class RoundTiming:
    """duration(n, K) = n (n - 1) (pair_idle_s + K exchange_s): one slot per ordered pair.

    pair_idle_s: the idle time after each pair (the ``F`` broadcast's RX timeout: 60 ms fitted;
    the firmware's ``dwt_setrxtimeout(65000)``, in UWB microseconds, is 66.7 ms plus a 1 ms
    sleep); exchange_s: one exchange (2.96 ms fitted, about 2.7 ms from the firmware's delays)."""

    pair_idle_s: float
    exchange_s: float

    @classmethod
    def fit(cls, config: CalibrationConfig) -> RoundTiming:
        """Solve the two constants exactly from the two reference latencies."""
        n = config.reference_n_anchors
        (k1, d1), (k2, d2) = config.reference_latencies_s
        pairs = n * (n - 1)
        exchange = (d2 - d1) / (pairs * (k2 - k1))
        idle = (d1 - pairs * k1 * exchange) / pairs
        if exchange <= 0 or idle < 0:
            raise ValueError(
                f"calibration.reference_latencies_s={config.reference_latencies_s!r}: "
                f"gives non-physical timing (exchange {exchange:.4g} s, pair idle {idle:.4g} s)"
            )
        return cls(pair_idle_s=float(idle), exchange_s=float(exchange))

    def pair_slot_s(self, measurements_per_pair: int) -> float:
        """One pair's share of a round: K exchanges, then the idle time."""
        return self.pair_idle_s + measurements_per_pair * self.exchange_s

    def duration_s(self, n_anchors: int, measurements_per_pair: int, n_initiators: int | None = None) -> float:
        m = n_anchors if n_initiators is None else n_initiators
        return m * (n_anchors - 1) * self.pair_slot_s(measurements_per_pair)

    def schedule(self, n_anchors: int, measurements_per_pair: int, initiators=None):
        """Per exchange: (time offset from round start (s), initiator, responder), in order
        (read-only arrays, shared by every round of the same shape).

        ``initiators``: the anchors that initiate, in turn (default: all, a team round)."""
        key = None if initiators is None else tuple(np.asarray(initiators, dtype=int).ravel().tolist())
        return _schedule(self, int(n_anchors), int(measurements_per_pair), key)


@functools.lru_cache(maxsize=256)
def _schedule(timing: RoundTiming, n: int, k: int, initiators: tuple | None):
    """``RoundTiming.schedule`` (a round of the same shape starts every few steps: built once)."""
    order = np.arange(n) if initiators is None else np.asarray(initiators, dtype=int)
    if order.size == 0 or order.min() < 0 or order.max() >= n or len(set(order.tolist())) != order.size:
        raise ValueError(f"initiators={list(initiators or ())!r}: must be distinct anchor indices in [0, {n})")
    pairs = np.array(pair_order(n, order), dtype=int).reshape(-1, 2)
    initiator, responder = np.repeat(pairs[:, 0], k), np.repeat(pairs[:, 1], k)
    # pair p's exchanges start at p slots, one exchange apart; its idle time follows them
    pair = np.repeat(np.arange(len(pairs)), k)
    times = pair * timing.pair_slot_s(k) + (np.tile(np.arange(k), len(pairs)) + 1) * timing.exchange_s
    for shared in (times, initiator, responder):
        shared.flags.writeable = False
    return times, initiator, responder


def pair_order(n: int, initiators=None) -> list[tuple[int, int]]:
    """The ordered pairs (initiator, responder) in the order a round ranges them: the
    ``initiators`` (default all, in index order) in turn, each polling the others in the
    firmware's counter-clockwise order i-1, i-2, ... (mod n) (``ss_init_main.c``: ID 1 -> 4, 3,
    2; ID 2 -> 1, 4, 3; ...)."""
    order = range(n) if initiators is None else initiators
    return [(int(i), (int(i) - s) % n) for i in order for s in range(1, n)]


def exchange_ranges(times_s, t0_s, t1_s, anchors_t0, anchors_t1, initiator, responder, range_model, rng):
    """Measured ranges of the exchanges at ``times_s`` in (t0, t1], the anchors' positions
    interpolated linearly over the step; ``anchors_t0/t1`` (n, dim), or (copies, n, dim) for
    a cohort of copies sharing the schedule."""
    a0, a1 = np.asarray(anchors_t0, dtype=float), np.asarray(anchors_t1, dtype=float)
    single = a0.ndim == 2
    d = _exchange_distances(np.asarray(times_s, dtype=float), float(t0_s), float(t1_s), a0[None] if single else a0,
                            a1[None] if single else a1, initiator, responder)
    return range_model.measure(d[0] if single else d, rng)


@njit(cache=True)
def _exchange_distances(times, t0, t1, a0, a1, initiator, responder):
    """(C, E) distances between each exchange's two anchors at its time, positions interpolated
    between a0 and a1 (C, n, dim): the numpy expression it replaced (alpha = (t - t0) /
    max(t1 - t0, 1e-12), p = a0 + alpha (a1 - a0), the norm's sum of squares in axis order)."""
    c_count, dim = a0.shape[0], a0.shape[2]
    span = max(t1 - t0, 1e-12)
    out = np.empty((c_count, len(times)))
    for c in range(c_count):
        for e in range(len(times)):
            alpha = (times[e] - t0) / span
            i, j = initiator[e], responder[e]
            d2 = 0.0
            for a in range(dim):
                pi = a0[c, i, a] + alpha * (a1[c, i, a] - a0[c, i, a])
                pj = a0[c, j, a] + alpha * (a1[c, j, a] - a0[c, j, a])
                d2 += (pi - pj) * (pi - pj)
            out[c, e] = math.sqrt(d2)
    return out


def busy_fraction(rnd, t0_s: float, t1_s: float, dt_s: float):
    """The fraction of the step (t0, t1] (of length ``dt_s``) that the round ``rnd`` (anything
    with ``start_time_s`` and ``end_time_s``: a round, a cohort, a hardware round) held the
    channel: the time the tags could not be ranged."""
    return (min(rnd.end_time_s, t1_s) - max(rnd.start_time_s, t0_s)) / dt_s


class CalibrationRound:
    """Collects the exchanges of one round as simulated time advances.

    Args:
        n_anchors: anchors taking part.
        timing: fitted round timing.
        measurements_per_pair: K.
        start_time_s: simulation time at which the start command was given.
        initiators: the anchors that initiate in turn (default all: a team round; one index:
            a per-anchor round).
    """

    def __init__(self, n_anchors: int, timing: RoundTiming, measurements_per_pair: int, start_time_s: float,
                 initiators=None):
        self.n_anchors = n_anchors
        offsets, self.initiator, self.responder = timing.schedule(n_anchors, measurements_per_pair, initiators)
        self.initiators = None if initiators is None else tuple(int(i) for i in initiators)
        self.times_s = start_time_s + offsets
        self.start_time_s = start_time_s
        n_init = None if initiators is None else len(self.initiators)
        self.end_time_s = start_time_s + timing.duration_s(n_anchors, measurements_per_pair, n_init)
        self.ranges_m = np.full(len(offsets), np.nan)
        self._next = 0
        self._time_s = start_time_s  # how far ``advance`` has taken the round

    @property
    def done(self) -> bool:
        """Every exchange taken and the round's time over: the last pair's ``F`` timeout holds
        the channel after its last exchange (up to ``pair_idle_s`` more)."""
        return self._next >= len(self.times_s) and self._time_s >= self.end_time_s - 1e-9

    @property
    def progress(self) -> float:
        return self._next / len(self.times_s)

    def advance(
        self,
        t0_s: float,
        t1_s: float,
        anchors_t0: np.ndarray,
        anchors_t1: np.ndarray,
        range_model: RangeModel,
        rng: np.random.Generator,
    ) -> None:
        """Take the exchanges timed in (t0, t1]; positions are interpolated linearly."""
        self._time_s = max(self._time_s, t1_s)
        stop = int(np.searchsorted(self.times_s, t1_s, side="right"))
        if stop <= self._next:
            return
        sl = slice(self._next, stop)
        self.ranges_m[..., sl] = exchange_ranges(self.times_s[sl], t0_s, t1_s, anchors_t0, anchors_t1,
                                                 self.initiator[sl], self.responder[sl], range_model, rng)
        self._next = stop

    def result(self) -> RangeMatrix:
        """Per ordered pair mean / std / count of the raw (uncorrected) ranges."""
        return RangeMatrix.from_samples(self.n_anchors, self.initiator, self.responder, self.ranges_m)
