"""Timing and measurement of one calibration round.

Every anchor is initiator in turn (index order, the paper's counter-clockwise order); each
initiator runs K SS-TWR exchanges with every other anchor, then hands the token on. Robots
keep moving, so each exchange ranges the positions at its own timestamp.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from uwb_env.config import CalibrationConfig
from uwb_env.measurements import RangeMatrix
from uwb_env.sim.ranging import RangeModel


@dataclass(frozen=True)
class RoundTiming:
    """duration(n, K) = n * handoff_s + n (n - 1) K * exchange_s."""

    handoff_s: float
    exchange_s: float

    @classmethod
    def fit(cls, config: CalibrationConfig) -> RoundTiming:
        """Solve the two constants exactly from the two reference latencies."""
        n = config.reference_n_anchors
        (k1, d1), (k2, d2) = config.reference_latencies_s
        pairs = n * (n - 1)
        exchange = (d2 - d1) / (pairs * (k2 - k1))
        handoff = (d1 - pairs * k1 * exchange) / n
        if exchange <= 0 or handoff < 0:
            raise ValueError(
                f"calibration.reference_latencies_s={config.reference_latencies_s!r}: "
                f"gives non-physical timing (exchange {exchange:.4g} s, handoff {handoff:.4g} s)"
            )
        return cls(handoff_s=float(handoff), exchange_s=float(exchange))

    def duration_s(self, n_anchors: int, measurements_per_pair: int) -> float:
        n, k = n_anchors, measurements_per_pair
        return n * self.handoff_s + n * (n - 1) * k * self.exchange_s

    def schedule(self, n_anchors: int, measurements_per_pair: int):
        """Per exchange: (time offset from round start (s), initiator, responder), in order."""
        n, k = n_anchors, measurements_per_pair
        initiator = np.repeat(np.arange(n), (n - 1) * k)
        responder_block = np.array([j for i in range(n) for j in range(n) if j != i]).reshape(n, n - 1)
        responder = np.repeat(responder_block, k, axis=1).ravel()
        index_in_block = np.tile(np.arange((n - 1) * k), n)
        times = (
            (initiator + 1) * self.handoff_s
            + (initiator * (n - 1) * k + index_in_block + 1) * self.exchange_s
        )
        return times, initiator, responder


class CalibrationRound:
    """Collects the exchanges of one round as simulated time advances.

    Args:
        n_anchors: anchors taking part.
        timing: fitted round timing.
        measurements_per_pair: K.
        start_time_s: simulation time at which the start command was given.
    """

    def __init__(self, n_anchors: int, timing: RoundTiming, measurements_per_pair: int, start_time_s: float):
        self.n_anchors = n_anchors
        offsets, self.initiator, self.responder = timing.schedule(n_anchors, measurements_per_pair)
        self.times_s = start_time_s + offsets
        self.start_time_s = start_time_s
        self.end_time_s = start_time_s + timing.duration_s(n_anchors, measurements_per_pair)
        self.ranges_m = np.full(len(offsets), np.nan)
        self._next = 0

    @property
    def done(self) -> bool:
        return self._next >= len(self.times_s)

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
        stop = int(np.searchsorted(self.times_s, t1_s, side="right"))
        if stop <= self._next:
            return
        sl = slice(self._next, stop)
        alpha = ((self.times_s[sl] - t0_s) / max(t1_s - t0_s, 1e-12))[:, None]
        i, j = self.initiator[sl], self.responder[sl]
        pi = anchors_t0[i] + alpha * (anchors_t1[i] - anchors_t0[i])
        pj = anchors_t0[j] + alpha * (anchors_t1[j] - anchors_t0[j])
        self.ranges_m[sl] = range_model.measure(np.linalg.norm(pi - pj, axis=1), rng)
        self._next = stop

    def result(self) -> RangeMatrix:
        """Per ordered pair mean / std / count of the raw (uncorrected) ranges."""
        return RangeMatrix.from_samples(self.n_anchors, self.initiator, self.responder, self.ranges_m)
