"""Fake DWM1001 devices that speak the real byte formats, driven by the simulator.

A :class:`Scene` runs a simulator :class:`~uwb_env.sim.World` in wall-clock time (ground
truth and the fitted range model). Devices are byte-level state machines:

- :class:`TiersAnchorDevice`: anchor ID 1 of the TIERS firmware (banner; ``S`` starts a round;
  the ordered pairs are ranged one after the other in the firmware's order, each where the
  robots are at that moment, a poll without an answer costing the initiator's RX timeout; the
  matrix of means and population stds of K ranges per ordered pair, in truncated centimetres).
- :class:`TiersTagDevice`: a tag of the TIERS localization build (banner, latched ``S``, one
  line per polling cycle, 255 bytes and the leaked partial sum of an anchor that times out).
- :class:`PansAnchorDevice`: a stock-PANS anchor that can be switched to tag mode and back
  (``acts``/``acas``/``nis``/``reset``/``si``), for the all-PANS deployment (:func:`pans_setup`).
- :class:`PansTagDevice`: a PANS tag in generic (TLV) mode after reset; ``\\r\\r`` enters the
  shell (banner, ``dwm> ``, echo, ``lec``/``lep``/``les`` toggles at the update rate, ``aurs``,
  ``quit``, ``reset``, empty line repeats); TLV ``dwm_loc_get``/``pos_get``/``cfg_get``/update
  rate; ``@\\x01\\x01`` for anything else in generic mode.

Ports: a pseudo-terminal per device (:class:`PtyPort`, the path is a real tty for any tool) or
a TCP server on 127.0.0.1 (:class:`SocketPort`, ``socket://127.0.0.1:PORT``) which can also
disappear and come back. :class:`Faults` injects garbage bytes, dropped characters, truncated
rows, a silent (hung) device, port loss and slow responses.
"""

from __future__ import annotations

import os
import select
import socket
import threading
import time
import tty
from dataclasses import dataclass

import numpy as np

from uwb_env.config import ConfigBase, SimConfig
from uwb_env.hardware import tlv
from uwb_env.hardware.pans_shell import AnchorRange, format_lec
from uwb_env.hardware.tiers import BANNER_INIT, ROLE_SWAP, RX_TIMEOUT_S, encode_matrix, firmware_pair_order
from uwb_env.hardware.tiers_tag import encode_tag_line
from uwb_env.sim import World


@dataclass(frozen=True)
class Faults(ConfigBase):
    """Fault injection per device (probabilities per output chunk unless stated)."""

    garbage_probability: float = 0.0
    drop_char_probability: float = 0.0  # per character
    truncate_row_probability: float = 0.0  # TIERS: per matrix, one row loses its tail
    hang: bool = False  # silent: no output, input ignored (a missing TIERS anchor)
    response_delay_s: float = 0.0  # extra latency before each output chunk
    round_slowdown: float = 1.0  # TIERS: rounds take this many times the timing model's duration
    # TIERS: each receiver misses a pair's finish (F) broadcast with this probability. ID 1 then
    # keeps that cell from an earlier round (stale); the next initiator missing its hand-over F
    # (or ID 1 the last one) hangs the round for good, as the firmware has no retry
    missed_f_probability: float = 0.0

    def __post_init__(self) -> None:
        for name in ("garbage_probability", "drop_char_probability", "truncate_row_probability",
                     "missed_f_probability"):
            self._probability(name)
        self._non_negative("response_delay_s")
        self._positive("round_slowdown")


class Scene:
    """The simulator's world stepped in wall-clock time; thread-safe.

    The world's motion and the range noise draw from two streams of the seed: how many world
    steps wall time allowed before a measurement (a loaded machine stalls a thread) then changes
    where the robots are, never which noise the next range gets."""

    def __init__(self, config: SimConfig | None = None, seed: int = 0, speedup: float = 1.0):
        self.config = config or SimConfig()
        self.world = World(self.config)
        world_seed, range_seed = np.random.SeedSequence(seed).spawn(2)
        self.rng = np.random.default_rng(range_seed)
        self.world.reset(np.random.default_rng(world_seed))
        self.speedup = speedup
        self._t0 = time.monotonic()
        self.lock = threading.Lock()

    def advance(self) -> None:
        with self.lock:
            target = (time.monotonic() - self._t0) * self.speedup
            while self.world.time_s + self.world.dt_s <= target:
                self.world.step()

    def anchors_true(self) -> np.ndarray:
        self.advance()
        with self.lock:
            return self.world.anchors_true.copy()

    def tags_true(self) -> np.ndarray:
        self.advance()
        with self.lock:
            return self.world.tags_true.copy()

    def measure(self, a: np.ndarray, b: np.ndarray, k: int, unbiased: bool = False,
                rng: np.random.Generator | None = None) -> np.ndarray:
        """k noisy ranges between points a and b (NaN for dropouts): with the fitted SS-TWR
        slope/offset bias of the TIERS firmware, or ``unbiased`` like antenna-delay calibrated
        stock PANS firmware. ``rng``: a device's own noise stream (default the scene's)."""
        d = np.full(k, float(np.linalg.norm(np.asarray(a) - np.asarray(b))))
        with self.lock:
            model = self.world.range_model
            raw = model.measure(d, self.rng if rng is None else rng)
            return np.maximum(model.undo_linear_bias(raw), 0.0) if unbiased else raw


def anchor_id4(index: int) -> str:
    return f"{0x1150 + index:04X}"


def emulated_anchor_ids(n: int = 4) -> list[str]:
    """The IDs the emulated PANS tags report for anchors 0..n-1 (``pans_anchor_ids`` of connect)."""
    return [anchor_id4(i) for i in range(n)]


class TiersAnchorDevice:
    """Anchor ID 1 of the TIERS autocalibration firmware (4 anchors: scene anchors 0..3).

    Modelled on ``Autocalibration/Initiator/main.c``: the main loop reads at most one byte per
    iteration into the start flag and advances the round only while that flag is ``S`` (another
    byte pauses it, a later ``S`` resumes it; an ``S`` during a round is absorbed: the flag is
    latched, there is no abort and no queue). At the end the matrix is printed, the firmware
    sleeps ``LAST_DELAY_MS`` (30 ms) and flushes its RX FIFO (input in that window is lost),
    then prints ``Waiting for Start order``.

    The round (``ss_init_main.c``) ranges the 12 ordered pairs one after the other in
    :func:`~uwb_env.hardware.tiers.firmware_pair_order`, each with the anchors where the scene
    has them when the pair starts (a moving team's pairs see different instants). A pair polls
    until K answers have arrived: a poll without an answer (a dropout; every poll, beyond the
    maximum range) holds the channel for the initiator's RX timeout, then the pair's result is
    broadcast, which also ends in that timeout. Pair durations: K answered polls plus one
    timeout plus one per unanswered poll, with the timeout taken as what makes the nominal round
    ``timing.duration_s(4, K)`` (60 ms against the firmware's 66.7 ms: the measured 0.9 s /
    2.5 s rounds at K = 5 / 50 both give it), and the answered poll as the fitted exchange time
    less its expected share of retries (the measured rounds include them: 1.7 ms of 3.0 ms at
    the default 2 % dropout), so rounds last the nominal time on average. A pair that gets no
    K answers within ``MAX_POLLS_PER_PAIR`` hangs the round, as the firmware, which retries
    forever. The matrix cells live across rounds (static RAM in the firmware), zero after a
    boot.

    The matrix ID 1 prints is its own copy: its three pairs computed locally, the other nine
    filled from the initiators' finish (``F``) broadcasts (``ss_resp_run``), each sent once and
    never acknowledged. With ``Faults.missed_f_probability`` ID 1 misses one now and then and
    prints that cell from an earlier round; a missed hand-over (the ``F`` an initiator sends
    to the next one after its last pair, or ID 4's last one to ID 1, which triggers the print)
    leaves nobody initiating: the round hangs until a reboot (``stale_cells``, ``hung`` count
    them).

    ``round_s`` overrides the nominal round duration (tests); ``round_id_in_std`` writes the
    round's number (cm) into std[0, 1] so tests can tell which round a matrix came from.
    """

    SETTLE_S = 0.030  # LAST_DELAY_MS before app_uart_flush()
    MAX_POLLS_PER_PAIR = 1000

    def __init__(self, scene: Scene, faults: Faults = Faults(), k: int | None = None, seed: int = 1,
                 round_s: float | None = None, round_id_in_std: bool = False):
        if scene.config.n_anchors != 4:
            raise ValueError(f"n_anchors={scene.config.n_anchors!r}: the TIERS firmware hard-wires 4 anchors")
        self.scene, self.faults = scene, faults
        self.k = k or scene.config.calibration.measurements_per_pair
        self.rng = np.random.default_rng(seed)
        # the round's range noise: its own stream, so that how many polls a round took (its
        # retries) never shifts the noise the tags' ranges get from the scene's
        self.range_rng = np.random.default_rng([seed, 1])
        self.round_s = round_s
        self.round_id_in_std = round_id_in_std
        self.out = bytearray((BANNER_INIT + "\r\n").encode())
        self._flag = b"0"
        self._progress_s = 0.0  # round time advanced while the flag was 'S'
        self._running = False
        self._last = None
        self._settle_until: float | None = None
        self._swap_sent = False
        self._pairs = firmware_pair_order()
        self._pair = 0  # next pair to range
        self._pair_start_s = 0.0  # round progress at which it starts
        self.pair_log: list[tuple[int, int, float]] = []  # (initiator, responder, round progress) ranged
        self.rounds = 0  # rounds started
        self.inputs_lost = 0  # bytes thrown away by the end-of-round flush
        self._mean = np.zeros((4, 4))
        self._std = np.zeros((4, 4))
        self.stale_cells = 0  # cells printed from an earlier round (a missed F broadcast)
        self.hung = 0  # rounds hung by a missed hand-over

    def reboot(self) -> None:
        """USB power cycle: the round in progress is gone, the matrix's RAM cleared; the boot
        banner is printed."""
        self._running, self._settle_until, self._flag = False, None, b"0"
        self._mean, self._std = np.zeros((4, 4)), np.zeros((4, 4))
        self.out = bytearray((BANNER_INIT + "\r\n").encode())

    def receive(self, data: bytes, now: float) -> None:
        if self.faults.hang or not data:
            return
        if self._settle_until is not None:  # app_uart_flush() empties the RX FIFO
            self.inputs_lost += len(data)
            return
        self._advance(now)
        self._flag = data[-1:]  # one byte per loop iteration: the last one read wins
        if self._flag == b"S" and not self._running:
            self._running, self._progress_s, self._swap_sent = True, 0.0, False
            self._pair, self._pair_start_s = 0, 0.0
            self.rounds += 1

    def _pair_timing(self) -> tuple[float, float]:
        """(one answered poll, the RX timeout) in seconds of round progress."""
        timing = self.scene.world.timing
        nominal = self.round_s if self.round_s is not None else timing.duration_s(4, self.k)
        slot = nominal * self.faults.round_slowdown / len(self._pairs)
        poll = timing.exchange_s * self.faults.round_slowdown
        timeout = slot - self.k * poll  # the fitted pair_idle_s (60 ms) at every K
        if timeout < 0.1 * slot:  # a round_s override shorter than the polls (tests): split the slot
            poll, timeout = 0.5 * slot / self.k, 0.5 * slot
        # The measured round lengths the timing model is fitted to include the firmware's
        # retries: its "exchange" is an answered poll plus its share of unanswered ones, q per
        # answer at the range model's dropout rate, each a timeout. So the expected round is the
        # nominal one (0.9 s / 2.5 s at K = 5 / 50), not that plus retries (2.5 -> 3.6 s).
        p = self.scene.config.ranging.dropout_probability
        q = p / (1.0 - p) if p < 1.0 else 0.0
        return max(poll - q * timeout, 0.0), timeout

    def _range_pair(self, i: int, j: int) -> float:
        """Range pair (i, j) now: store its mean and population std; return how long it holds
        the channel (inf: it never gets K answers, the round hangs)."""
        pos = self.scene.anchors_true()
        answers: list[float] = []
        unanswered = 0
        while len(answers) < self.k:
            if len(answers) + unanswered >= self.MAX_POLLS_PER_PAIR:
                return np.inf
            for r in self.scene.measure(pos[i], pos[j], self.k, rng=self.range_rng).tolist():
                if len(answers) == self.k:
                    break
                if np.isfinite(r):
                    answers.append(r)
                else:
                    unanswered += 1
        got = np.array(answers)
        # ID 1 (index 0) stores its own pairs; the others reach its copy by the F broadcast
        heard = i == 0 or not self._misses_f()
        if heard:
            self._mean[i, j], self._std[i, j] = got.mean(), got.std()  # population std, as the firmware
        # an initiator's last F is addressed to its last responder, the next initiator (ID 1 after
        # ID 4: the same frame that fills that cell makes it print)
        last_of_initiator = self._pair + 1 == len(self._pairs) or self._pairs[self._pair + 1][0] != i
        if last_of_initiator and (not heard if j == 0 else self._misses_f()):
            self.hung += 1  # nobody initiates: the round never ends
            return np.inf
        self.stale_cells += not heard
        poll_s, timeout_s = self._pair_timing()
        return self.k * poll_s + unanswered * timeout_s + timeout_s

    def _misses_f(self) -> bool:
        p = self.faults.missed_f_probability
        return p > 0.0 and self.rng.random() < p

    def _advance(self, now: float) -> None:
        if self._running and self._flag == b"S" and self._last is not None:
            self._progress_s += now - self._last
        self._last = now

    def poll(self, now: float) -> bytes:
        if self.faults.hang:
            self.out.clear()
            return b""
        self._advance(now)
        if self._settle_until is not None and now >= self._settle_until:
            self._settle_until, self._flag = None, b"0"
            self.out += b"Waiting for Start order\r\n"
        while self._running and self._progress_s >= self._pair_start_s:
            if self._pair == len(self._pairs):  # the last pair's broadcast timed out: print
                self.out += self._matrix()
                self._running = False
                self._settle_until = now + self.SETTLE_S
                break
            initiator, responder = self._pairs[self._pair]
            if initiator != 0 and not self._swap_sent:  # ID 1's pairs done: it becomes a responder
                self.out += (ROLE_SWAP + "\r\n").encode()
                self._swap_sent = True
            self.pair_log.append((initiator, responder, self._pair_start_s))
            self._pair_start_s += self._range_pair(initiator, responder)
            self._pair += 1
        data, self.out = bytes(self.out), bytearray()
        return _apply_faults(data, self.faults, self.rng)

    def _matrix(self) -> bytes:
        mean, std = self._mean.copy(), self._std.copy()
        if self.round_id_in_std:
            std[0, 1] = self.rounds / 100.0
        text = encode_matrix(mean, std).split(b" Waiting for Start order")[0]  # printed after the flush
        if self.rng.random() < self.faults.truncate_row_probability:
            lines = text.split(b"\r\n")
            row = int(self.rng.integers(0, 4))
            lines[row] = lines[row][: len(lines[row]) // 2]  # TX-FIFO overflow drops the tail
            text = b"\r\n".join(lines)
        return text


class TiersTagDevice:
    """A tag running the TIERS localization build (ID 0), ranging to scene anchors 0..3 (IDs 1..4).

    Modelled on ``Localization/Initiator/main.c`` and ``ss_init_main.c``: after power-up the
    banner, then nothing until ``S``; the flag is latched (one poll per main-loop iteration
    while the last byte read is ``S``, another byte pauses, ``F`` prints ``END`` and stops the
    tag until a reboot). Each anchor in turn gets polls until 5 answers (one SS-TWR exchange
    plus the 1 ms inter-ranging delay each) or 25 failed polls in a row (66.7 ms RX timeout each:
    255 bytes). The running sum is reset only after an anchor that answered 5 times, so a
    timed-out anchor's partial sum leaks into the next anchor's mean (the firmware's quirk).
    ``silent_after``: anchor ID -> answers it gives per cycle before falling silent
    (``{3: 0}``: anchor 3 never answers); ranges are the SS-TWR ranges with the fitted bias.
    """

    RX_TIMEOUT_S = RX_TIMEOUT_S  # dwt_setrxtimeout(65000) in main.c: 65,000 UWB us (512/499.2 MHz) = 66.7 ms
    RNG_DELAY_S = 0.001  # RNG_DELAY_MS
    MAX_ITER, TIMEOUT_POLLS = 5, 25

    def __init__(self, scene: Scene, tag_index: int, faults: Faults = Faults(), seed: int = 3,
                 silent_after: dict[int, int] | None = None):
        if scene.config.n_anchors != 4:
            raise ValueError(f"n_anchors={scene.config.n_anchors!r}: the TIERS tag build polls exactly 4 anchors")
        self.scene, self.tag_index, self.faults = scene, tag_index, faults
        self.rng = np.random.default_rng(seed + tag_index)
        self.silent_after = dict(silent_after or {})
        self.exchange_s = scene.world.timing.exchange_s
        self.lines = 0
        self.reboot()

    def reboot(self) -> None:
        self.out = bytearray((BANNER_INIT + "\r\n").encode())
        self._flag, self._stopped = b"0", False
        self._resp, self._iter, self._timeouts, self._total = 1, 0, 0, 0.0
        self._answers = 0
        self._measurements = np.zeros(self.MAX_ITER)
        self._row_means: list[float] = []
        self._row_stds: list[float] = []
        self._clock: float | None = None

    def receive(self, data: bytes, now: float) -> None:
        if self.faults.hang or not data or self._stopped:
            return
        self._run(now)
        self._flag = data[-1:]
        if self._flag == b"F":
            self.out += b"END\r\n"
            self._stopped = True
        elif self._flag == b"S" and self._clock is None:
            self._clock = now

    def poll(self, now: float) -> bytes:
        if self.faults.hang:
            self.out.clear()
            return b""
        self._run(now)
        data, self.out = bytes(self.out), bytearray()
        return _apply_faults(data, self.faults, self.rng)

    def _run(self, now: float) -> None:
        if self._stopped or self._flag != b"S" or self._clock is None:
            self._clock = now if self._flag == b"S" else None
            return
        while self._clock < now:
            self._clock += self._poll_once()

    def _poll_once(self) -> float:
        """One ss_init_run(): returns the time it took."""
        limit = self.silent_after.get(self._resp)
        anchor = self.scene.anchors_true()[self._resp - 1]
        tag = self.scene.tags_true()[self.tag_index]
        r = np.nan if limit is not None and self._answers >= limit else self.scene.measure(anchor, tag, 1)[0]
        if np.isfinite(r):
            self._measurements[self._iter] = r
            self._total += r
            self._iter, self._timeouts, self._answers = self._iter + 1, 0, self._answers + 1
            took = self.exchange_s + self.RNG_DELAY_S
        else:
            self._timeouts += 1
            took = self.RX_TIMEOUT_S + self.RNG_DELAY_S
        if self._iter >= self.MAX_ITER or self._timeouts == self.TIMEOUT_POLLS:
            if self._timeouts == self.TIMEOUT_POLLS:
                self._row_means.append(np.nan)  # 255 bytes; the running sum is NOT reset (firmware)
                self._row_stds.append(np.nan)
            else:
                mean = self._total / self.MAX_ITER
                self._total = 0.0
                self._row_means.append(mean)
                self._row_stds.append(float(np.sqrt(np.mean((self._measurements - mean) ** 2))))
            self._resp, self._iter, self._timeouts, self._answers = self._resp + 1, 0, 0, 0
            if self._resp > 4:
                self.out += encode_tag_line(self._row_means, self._row_stds)
                self.lines += 1
                self._resp, self._row_means, self._row_stds = 1, [], []
        return took


class PansTagDevice:
    """A PANS tag (scene tag ``tag_index``) ranging to the scene's first 4 anchors."""

    BANNER = (b"\r\n DWM1001 TWR Real Time Location System\r\n\r\n Copyright :  2016-2019 LEAPS and Decawave\r\n"
              b" License   :  Please visit https://decawave.com/dwm1001_license\r\n"
              b" Compiled  :  Mar 27 2019 03:35:59\r\n\r\n Help      :  ? or help\r\n\r\n")

    def __init__(self, scene: Scene, tag_index: int, faults: Faults = Faults(), seed: int = 2,
                 glue_prompt: bool = True):
        self.scene, self.tag_index, self.faults = scene, tag_index, faults
        self.rng = np.random.default_rng(seed + tag_index)
        self.mode = "generic"
        self.out = bytearray()
        self._line = b""
        self._last_cr = -np.inf
        self._last_command = ""
        self.streams: set[str] = set()
        self.update_rate_100ms, self.stationary_100ms = 1, 5
        self._next_report = 0.0
        self.glue_prompt = glue_prompt
        self._glue_next = False
        self._generic = b""

    def reboot(self) -> None:
        """Power cycle / USB re-enumeration: back in generic (TLV) mode, streams off."""
        self.mode, self.streams, self._line, self._last_command = "generic", set(), b"", ""
        self.out.clear()

    # -- input ---------------------------------------------------------------------------------
    def receive(self, data: bytes, now: float) -> None:
        if self.faults.hang:
            return
        for b in data:
            if self.mode == "generic":
                self._generic_byte(bytes([b]), now)
            else:
                self._shell_byte(bytes([b]), now)

    def _generic_byte(self, b: bytes, now: float) -> None:
        if b == b"\r":
            if now - self._last_cr <= 1.0:  # two Enters within 1 s: shell mode
                self.mode, self._generic = "shell", b""
                self.out += self.BANNER + b"dwm> "
                return
            self._last_cr = now
            return
        self._generic += b
        buf = self._generic
        if len(buf) >= 2 and len(buf) >= 2 + buf[1]:
            self._generic = b""
            self.out += self._tlv(buf[0], buf[2:2 + buf[1]]) if len(buf) == 2 + buf[1] else b"@\x01\x01"
        elif len(buf) >= 2 and not 0 < buf[0] < 0x40:  # not a request type we know: text typed in generic mode
            self._generic = b""
            self.out += b"@\x01\x01"

    def _shell_byte(self, b: bytes, now: float) -> None:
        if b in (b"\r", b"\n"):
            if b == b"\n":
                return
            self.out += b"\r\n"
            command = self._line.decode(errors="replace").strip() or self._last_command
            self._line = b""
            self._last_command = command
            self._execute(command, now)
            return
        self._line += b
        self.out += b  # echo

    def _execute(self, command: str, now: float) -> None:
        name, *args = command.split() or [""]
        if name in ("lec", "lep", "les"):
            self.streams ^= {name}  # toggles
            self._next_report = now
            self._glue_next = self.glue_prompt
            if self._glue_next:
                self.out += b"dwm> "  # the prompt ends up glued to the first report line
                return
        elif name == "quit":
            self.mode = "generic"
            return
        elif name == "reset":
            self.mode, self.streams = "generic", set()
            return
        elif name == "aurs" and len(args) == 2 and all(a.isdigit() for a in args):
            self.update_rate_100ms, self.stationary_100ms = max(int(args[0]), 1), int(args[1])
            self.out += b"err code: 0\r\n"
        elif name == "aurg":
            self.out += f"err code: 0, upd rate: {self.update_rate_100ms}, {self.stationary_100ms}(stat)\r\n".encode()
        elif name == "apg":
            x, y, z = self._position_mm()
            self.out += f"x:{x} y:{y} z:{z} qf:100\r\n".encode()
        elif name:
            self.out += f"{name}: unknown command\r\n".encode()
        self.out += b"dwm> "

    # -- output --------------------------------------------------------------------------------
    def poll(self, now: float) -> bytes:
        if self.faults.hang:
            self.out.clear()
            return b""
        if self.mode == "shell" and self.streams and now >= self._next_report:
            self._next_report = now + 0.1 * self.update_rate_100ms
            line = self._report()
            if self._glue_next:
                self._glue_next = False
            self.out += line.encode() + b"\r\n"
        data, self.out = bytes(self.out), bytearray()
        return _apply_faults(data, self.faults, self.rng)

    def _ranges(self) -> list[AnchorRange]:
        anchors = self.scene.anchors_true()[:4]
        tag = self.scene.tags_true()[self.tag_index]
        out = []
        for i, a in enumerate(anchors):
            d = self.scene.measure(a, tag, 1, unbiased=True)[0]
            if np.isfinite(d):
                pos = tuple(np.r_[a, np.zeros(3 - len(a))])
                out.append(AnchorRange(anchor_id4(i), pos, float(d)))
        return out

    def _position_mm(self) -> tuple[int, int, int]:
        p = np.r_[self.scene.tags_true()[self.tag_index], 0.0, 0.0][:3]
        return tuple(int(round(v * 1000)) for v in p)

    def _report(self) -> str:
        ranges = self._ranges()
        tag = np.r_[self.scene.tags_true()[self.tag_index], 0.0, 0.0][:3]
        qf = 100 if len(ranges) >= 4 else (50 if len(ranges) == 3 else None)
        pos = tag if qf is not None else None
        if "lec" in self.streams:
            return format_lec(ranges, pos, qf)
        if "lep" in self.streams:
            return f"POS,{tag[0]:.2f},{tag[1]:.2f},{tag[2]:.2f},{qf or 0}"
        groups = " ".join(f"{r.anchor_id}[{r.position_m[0]:.2f},{r.position_m[1]:.2f},{r.position_m[2]:.2f}]"
                          f"={r.distance_m:.2f}" for r in ranges)
        return groups + (f" le_us=2576 est[{tag[0]:.2f},{tag[1]:.2f},{tag[2]:.2f},{qf}]" if qf else "")

    def _tlv(self, type_: int, value: bytes) -> bytes:
        ok = tlv.encode(tlv.RET_VAL, b"\x00")
        x, y, z = self._position_mm()
        pos = tlv.Position(x / 1000, y / 1000, z / 1000, 100)
        if type_ == tlv.LOC_GET and not value:
            dists = [tlv.Distance(int(r.anchor_id, 16), r.distance_m, 100, tlv.Position(*r.position_m, 100))
                     for r in self._ranges()]
            return tlv.encode_location_tag(pos, dists)
        if type_ == tlv.POS_GET and not value:
            return ok + tlv.encode(tlv.POS_XYZ, pos.pack())
        if type_ == tlv.CFG_GET and not value:
            return ok + tlv.encode(tlv.CFG, bytes([0x40 | 0x10 | 0x02, 0x00]))  # tag, loc engine, LED, active
        if type_ == tlv.UPD_RATE_GET and not value:
            return ok + tlv.encode(tlv.UPD_RATE, int(self.update_rate_100ms).to_bytes(2, "little")
                                   + int(self.stationary_100ms).to_bytes(2, "little"))
        if type_ == tlv.UPD_RATE_SET and len(value) == 4:
            self.update_rate_100ms = max(int.from_bytes(value[:2], "little"), 1)
            self.stationary_100ms = int.from_bytes(value[2:], "little")
            return ok
        return tlv.encode(tlv.RET_VAL, b"\x01")


class PansAnchorDevice(PansTagDevice):
    """A stock-PANS anchor (scene anchor ``anchor_index``, ID ``anchor_id4(anchor_index)``) that
    can be switched to tag mode and back, as host scripts do to survey anchors with stock
    firmware (``esauortiz/dwm1001_drivers:scripts/autocalibration_sample_uart.py``):
    ``acts <9 flags>`` / ``acas <7 flags>`` store the next role, ``nis 0x....`` the network,
    ``reset`` reboots into it (generic mode, silent for ``boot_s``). ``si`` prints the node's
    address and mode. In tag mode ``lec``/``les`` stream ranges to the other anchors (at most 4,
    the nearest, as a PANS tag picks them); in anchor mode the streams print nothing.
    """

    def __init__(self, scene: Scene, anchor_index: int, faults: Faults = Faults(), seed: int = 5,
                 boot_s: float = 0.3, network_id: int = 0x1234):
        super().__init__(scene, anchor_index, faults, seed, glue_prompt=False)
        self.anchor_index, self.boot_s = anchor_index, boot_s
        self.role, self._next_role = "anchor", "anchor"
        self.network_id = self._next_network = network_id
        self._booting_until = -np.inf
        self.role_switches = 0

    def receive(self, data: bytes, now: float) -> None:
        if now < self._booting_until:
            return  # still booting: the UART is not up
        super().receive(data, now)

    def poll(self, now: float) -> bytes:
        if now < self._booting_until:
            return b""
        if self.role == "anchor":
            self._next_report = np.inf  # anchors do not range as tags: the streams print nothing
        return super().poll(now)

    def _execute(self, command: str, now: float) -> None:
        name, *args = command.split() or [""]
        ints = all(a.lstrip("-").isdigit() for a in args)
        if name == "acts" and len(args) == 9 and ints:
            self._next_role = "tag"
        elif name == "acas" and len(args) == 7 and ints:
            self._next_role = "anchor"
        elif name == "nis" and len(args) == 1 and args[0].lower().startswith("0x"):
            self._next_network = int(args[0], 16)
        elif name == "si":
            mode = "tn (act,twr,np,le)" if self.role == "tag" else "an (act,-,-)"
            addr = f"DECA00000000{anchor_id4(self.anchor_index)}"
            self.out += (f"[000001.000 INF] sys: fw2 fw_ver=x01020001 cfg_ver=x00010700\r\n"
                         f"[000001.000 INF] uwb0: panid=x{self.network_id:04X} addr=x{addr}\r\n"
                         f"[000001.000 INF] mode: {mode}\r\n").encode()
        elif name == "reset":
            if self._next_role != self.role:
                self.role_switches += 1
            self.role, self.network_id = self._next_role, self._next_network
            self.reboot()  # RAM state (streams, the line, the last command) is gone
            self._booting_until = now + self.boot_s
            return
        else:
            super()._execute(command, now)
            return
        if name in ("acts", "acas", "nis"):
            self.out += b"err code: 0\r\n"
        self.out += b"dwm> "

    def _ranges(self) -> list[AnchorRange]:
        anchors = self.scene.anchors_true()
        me = anchors[self.anchor_index]
        order = [i for i in np.argsort(np.linalg.norm(anchors - me, axis=1)) if i != self.anchor_index][:4]
        out = []
        for i in sorted(order):
            d = self.scene.measure(anchors[i], me, 1, unbiased=True)[0]
            if np.isfinite(d):
                out.append(AnchorRange(anchor_id4(int(i)), tuple(np.r_[anchors[i], np.zeros(3 - len(anchors[i]))]),
                                       float(d)))
        return out

    def _position_mm(self) -> tuple[int, int, int]:
        p = np.r_[self.scene.anchors_true()[self.anchor_index], 0.0, 0.0][:3]
        return tuple(int(round(v * 1000)) for v in p)

    def _report(self) -> str:
        return format_lec(self._ranges(), None, None)  # acts ... loc_engine 0: no position


def pans_setup(scene: Scene, faults: dict[str, Faults] | None = None, transport: str = "pty", seed: int = 0,
               boot_s: float = 0.3) -> tuple[Emulator, dict[str, str]]:
    """The all-PANS deployment: a stock-PANS anchor per scene anchor (``anchor_0`` ...) and a
    PANS tag per scene tag (``tag_0`` ...), each on its own port: name -> URL."""
    faults = faults or {}
    emu = Emulator(scene)
    make = (lambda: SocketPort()) if transport == "socket" else (lambda: PtyPort())
    urls = {}
    for i in range(scene.config.n_anchors):
        name = f"anchor_{i}"
        urls[name] = emu.add(name, PansAnchorDevice(scene, i, faults.get(name, Faults()), seed=seed + 5,
                                                    boot_s=boot_s), make())
    for t in range(scene.config.n_tags):
        name = f"tag_{t}"
        urls[name] = emu.add(name, PansTagDevice(scene, t, faults.get(name, Faults()), seed=seed + 2), make())
    return emu, urls


def _apply_faults(data: bytes, faults: Faults, rng: np.random.Generator) -> bytes:
    if not data:
        return data
    if faults.response_delay_s > 0:
        time.sleep(faults.response_delay_s)
    if faults.drop_char_probability > 0:
        keep = rng.random(len(data)) >= faults.drop_char_probability
        data = bytes(np.frombuffer(data, dtype=np.uint8)[keep])
    if faults.garbage_probability > 0 and rng.random() < faults.garbage_probability:
        at = int(rng.integers(0, len(data) + 1))
        data = data[:at] + rng.integers(0, 256, int(rng.integers(1, 8)), dtype=np.uint8).tobytes() + data[at:]
    return data


# -- ports ----------------------------------------------------------------------------------------
class PtyPort:
    """A pseudo-terminal: the device holds the master; ``url`` is the slave's path."""

    def __init__(self):
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)  # no echo, no CR/LF translation: bytes as a UART delivers them
        self.url = os.ttyname(self.slave)

    def read(self, timeout_s: float) -> bytes:
        ready, _, _ = select.select([self.master], [], [], timeout_s)
        return os.read(self.master, 4096) if ready else b""

    def write(self, data: bytes) -> None:
        os.write(self.master, data)

    def close(self) -> None:
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass


class SocketPort:
    """A TCP endpoint on 127.0.0.1 for ``socket://``; ``unplug(s)`` drops the link and refuses
    connections for ``s`` seconds, like a USB device that disappears and re-enumerates."""

    def __init__(self, port: int = 0):
        self._server = self._listen(port)
        self.port = self._server.getsockname()[1]
        self.url = f"socket://127.0.0.1:{self.port}"
        self._conn: socket.socket | None = None
        self._down_until = 0.0
        self._pending_unplug: float | None = None
        self.connections = 0
        self.unplugs = 0

    @staticmethod
    def _listen(port: int) -> socket.socket:
        s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind(("127.0.0.1", port))
        s.listen(1)
        s.setblocking(False)
        return s

    def unplug(self, seconds: float) -> None:
        """Thread-safe: the serving thread carries it out at its next read."""
        self._pending_unplug = seconds

    def _do_unplug(self, seconds: float) -> None:
        self.unplugs += 1
        self._down_until = time.monotonic() + seconds
        if self._conn is not None:
            self._conn.close()
            self._conn = None
        if self._server is not None:
            self._server.close()
            self._server = None

    def _accept(self) -> None:
        if self._server is None:
            if time.monotonic() < self._down_until:
                return
            self._server = self._listen(self.port)
        try:
            conn, _ = self._server.accept()
        except BlockingIOError:
            return
        conn.setblocking(False)
        self._conn = conn
        self.connections += 1

    def read(self, timeout_s: float) -> bytes:
        if self._pending_unplug is not None:
            self._do_unplug(self._pending_unplug)
            self._pending_unplug = None
        if self._conn is None:
            self._accept()
            if self._conn is None:
                time.sleep(timeout_s)
                return b""
        ready, _, _ = select.select([self._conn], [], [], timeout_s)
        if not ready:
            return b""
        try:
            data = self._conn.recv(4096)
        except OSError:
            data = b""
        if not data:  # the client went away
            self._conn.close()
            self._conn = None
        return data

    @property
    def connected(self) -> bool:
        return self._conn is not None

    def write(self, data: bytes) -> None:
        if self._conn is None or not data:
            return
        try:
            self._conn.sendall(data)
        except OSError:
            self._conn.close()
            self._conn = None

    def close(self) -> None:
        for s in (self._conn, self._server):
            if s is not None:
                s.close()


class Emulator:
    """Serves devices on ports, one thread each; ``with Emulator(...) as emu:``."""

    def __init__(self, scene: Scene, tick_s: float = 0.002):
        self.scene, self.tick_s = scene, tick_s
        self.ports: dict[str, object] = {}
        self.devices: dict[str, object] = {}
        self._threads: list[threading.Thread] = []
        self._stop = threading.Event()

    def add(self, name: str, device, port=None) -> str:
        port = port or PtyPort()
        self.ports[name], self.devices[name] = port, device
        t = threading.Thread(target=self._serve, args=(device, port), name=f"emulator {name}", daemon=True)
        self._threads.append(t)
        t.start()
        return port.url

    def _serve(self, device, port) -> None:
        unplugs = getattr(port, "unplugs", 0)
        while not self._stop.is_set():
            data = port.read(self.tick_s)
            if getattr(port, "unplugs", 0) != unplugs and getattr(port, "connected", False):
                # USB-powered boards lose power with the cable: the device boots again when the
                # port comes back (and the host has reopened it, so the boot output is seen)
                unplugs = port.unplugs
                if hasattr(device, "reboot"):
                    device.reboot()
            now = time.monotonic()
            if data:
                device.receive(data, now)
            out = device.poll(now)
            if out:
                try:
                    port.write(out)
                except OSError:
                    pass

    def close(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(timeout=1.0)
        for port in self.ports.values():
            port.close()

    def __enter__(self) -> Emulator:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def standard_setup(scene: Scene, faults: dict[str, Faults] | None = None, transport: str = "pty",
                   seed: int = 0, tag_firmware: str = "pans") -> tuple[Emulator, dict[str, str]]:
    """One TIERS anchor (``anchor``) and a tag per scene tag (``tag_0`` ...): name -> URL.

    ``tag_firmware``: ``"pans"`` (stock PANS tags, ranging to a PANS anchor set) or ``"tiers"``
    (the TIERS localization build, ranging to the TIERS anchors themselves: all-TIERS)."""
    if tag_firmware not in ("pans", "tiers"):
        raise ValueError(f"tag_firmware={tag_firmware!r}: expected 'pans' or 'tiers'")
    faults = faults or {}
    emu = Emulator(scene)
    make = (lambda: SocketPort()) if transport == "socket" else (lambda: PtyPort())
    urls = {"anchor": emu.add("anchor", TiersAnchorDevice(scene, faults.get("anchor", Faults()), seed=seed + 1),
                              make())}
    for t in range(scene.config.n_tags):
        name = f"tag_{t}"
        kind = TiersTagDevice if tag_firmware == "tiers" else PansTagDevice
        urls[name] = emu.add(name, kind(scene, t, faults.get(name, Faults()), seed=seed + 2), make())
    return emu, urls
