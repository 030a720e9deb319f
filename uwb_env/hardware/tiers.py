"""Codec of the TIERS autocalibration firmware (the paper's), pure bytes in, messages out.

Host -> anchor ID 1: the single byte ``S`` starts one round (never a line ending: any later
byte aborts the round). Anchor 1 -> host, per round::

    responder becomes initiator and viceversa\\r\\n
    R0\\r\\n R1\\r\\n R2\\r\\n R3\\r\\n \\r\\n Waiting for Start order\\r\\n

where ``Rk`` are 16 ``"%d , "`` tokens: for responder j, ``mean_msb, mean_lsb, std_msb,
std_lsb`` in centimetres (truncated, uint8). Row = initiator ID - 1, column = responder ID - 1.
A row that is not exactly 16 integers in 0..255 (TX-FIFO overflow drops characters) makes the
whole matrix rejected, never misread. A negative mean wraps (uint8): :func:`unwrap_negative_means`
undoes it where the reverse direction of the pair tells.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from uwb_env.hardware.errors import ParseError
from uwb_env.sim.calibration_round import pair_order

START = b"S"
N_DEVICES = 4  # the firmware hard-wires a 4x4 matrix
BANNER_INIT = "Singled Sided Two Way Ranging INIT"
BANNER_RESP = "Singled Sided Two Way Ranging RESP"
ROLE_SWAP = "responder becomes initiator and viceversa"
WAITING = "Waiting for Start order"
_ROW = re.compile(r"^\s*(?:\d{1,3}\s*,\s*){16}$")
_ROWISH = re.compile(r"^[\s\d,]*\d[\s\d,]*$")  # digits, commas, spaces only: a (maybe broken) row

# The initiator's RX timeout (``dwt_setrxtimeout(65000)`` UUS, 1 UUS = 512/499.2 us): how long a
# poll that gets no answer, and the broadcast of a pair's result (sent expecting a response
# that never comes), hold the channel.
RX_TIMEOUT_S = 65000 * 512 / 499.2e6


def firmware_pair_order(n: int = N_DEVICES) -> list[tuple[int, int]]:
    """The ordered pairs (initiator, responder), 0-based, in the order a round ranges them.

    ``Autocalibration/*/ss_init_main.c``: anchors are initiators in ID order; initiator ID i
    polls the responders "in counter-clockwise order" i-1, i-2, i-3 (mod 4: ID 1 -> 4, 3, 2;
    ID 2 -> 1, 4, 3; ID 3 -> 2, 1, 4; ID 4 -> 3, 2, 1), each until MAX_ITER answers have
    arrived, then broadcasts that pair's mean and std (``F`` frame) and moves on. The
    simulator's rounds use the same order (``sim.calibration_round.pair_order``)."""
    return pair_order(n)


@dataclass(frozen=True)
class Banner:
    text: str


@dataclass(frozen=True)
class RoleSwap:
    pass


@dataclass(frozen=True)
class WaitingForStart:
    pass


@dataclass(frozen=True)
class RangeMatrixMessage:
    """One round's matrix: (4, 4) mean and std in metres (diagonal 0). ``repeated`` (set by
    :class:`~uwb_env.hardware.drivers.TiersAnchorDriver`; None from the decoder): cells whose
    mean and std both repeat the matrix the firmware printed before, byte for byte: possibly
    stale (a missed ``F`` broadcast leaves ID 1's copy of that cell from an earlier round)."""

    mean_m: np.ndarray
    std_m: np.ndarray
    repeated: np.ndarray | None = None

    def __eq__(self, other):
        return (isinstance(other, RangeMatrixMessage) and np.array_equal(self.mean_m, other.mean_m)
                and np.array_equal(self.std_m, other.std_m))


def repeated_cells(previous: RangeMatrixMessage | None, message: RangeMatrixMessage) -> np.ndarray:
    """(4, 4) bool: the filled cells of ``message`` whose mean and std both equal ``previous``'s
    (the matrix the firmware printed before it; None: unknown, nothing is flagged).

    ID 1 prints its own copy of the matrix: its pairs computed locally, the others' written
    when their initiator's finish (``F``) broadcast arrives (``ss_resp_run``, sent once, never
    acknowledged), and nothing clears a cell between rounds. A missed broadcast therefore
    reprints the earlier value, byte for byte; a fresh cell repeats both its centimetre mean
    and std by chance only now and then (about 2 % of cells of a still team in the emulator)."""
    if previous is None:
        return np.zeros(np.shape(message.mean_m), dtype=bool)
    return (message.mean_m == previous.mean_m) & (message.std_m == previous.std_m) & (message.mean_m != 0)


@dataclass(frozen=True)
class RejectedMatrix:
    """A matrix that arrived damaged (truncated or malformed row); ``reason`` says how."""

    reason: str


@dataclass(frozen=True)
class OtherLine:
    text: str


def parse_row(line: str) -> np.ndarray:
    """16 uint8 tokens of one matrix row -> (4, 4) array [responder, (mean_msb, mean_lsb, sd_msb, sd_lsb)]."""
    if not _ROW.match(line):
        raise ParseError("TIERS matrix row: expected 16 comma-terminated integers", line)
    values = [int(tok) for tok in line.replace(" ", "").split(",")[:16]]
    if max(values) > 255:
        raise ParseError("TIERS matrix row: value above 255", line)
    return np.array(values, dtype=np.int64).reshape(N_DEVICES, 4)


def decode_cells(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(4, 4, 4) uint8 cells -> mean, std in metres (value = (msb * 256 + lsb) / 100)."""
    mean = (rows[..., 0] * 256 + rows[..., 1]) / 100.0
    std = (rows[..., 2] * 256 + rows[..., 3]) / 100.0
    return mean, std


WRAP_M = 2.56  # a negative mean in (-2.56, 0) m is printed as msb 0, lsb 256 + cm: read as mean + 2.56


def unwrap_negative_means(mean_m: np.ndarray, tolerance_m: float = 0.3,
                          window_m: float = 0.5) -> tuple[np.ndarray, int, int]:
    """Undo the uint8 wrap of negative means (possible after antenna-delay errors at very short
    range, down to about ``-window_m``) where the matrix itself tells. A cell read in
    [2.56 - window_m, 2.56) m may be a negative mean + 2.56. It is unwrapped when its unwrapped
    value agrees with the reverse direction of the same pair (within ``tolerance_m``) and the
    read value does not. When both directions read alike, a third anchor decides: two anchors
    a few centimetres apart are at the same distance from every other anchor, so one anchor
    whose two distances differ by more than ``window_m`` + ``tolerance_m`` shows the pair is
    genuine. Returns (means, cells unwrapped, pairs left ambiguous).
    """
    mean = np.array(mean_m, dtype=float)
    n = mean.shape[0]
    unwrapped = ambiguous = 0
    candidate = (mean >= WRAP_M - window_m) & (mean < WRAP_M)
    for i in range(n):
        for j in range(i + 1, n):
            ci, cj = candidate[i, j], candidate[j, i]
            if not (ci or cj):
                continue
            if ci and cj and abs(mean[i, j] - mean[j, i]) <= tolerance_m:
                others = [k for k in range(n) if k not in (i, j)]
                spread = [abs(np.nanmean([mean[i, k], mean[k, i]]) - np.nanmean([mean[j, k], mean[k, j]]))
                          for k in others]
                if not any(d > window_m + tolerance_m for d in spread):
                    ambiguous += 1  # co-located or on the perpendicular bisector: not guessed
                continue
            for a, b in ((i, j), (j, i)):
                if candidate[a, b] and abs(mean[a, b] - WRAP_M - mean[b, a]) <= tolerance_m < abs(
                        mean[a, b] - mean[b, a]):
                    mean[a, b] -= WRAP_M
                    unwrapped += 1
    return mean, unwrapped, ambiguous


def encode_matrix(mean_m: np.ndarray, std_m: np.ndarray) -> bytes:
    """The firmware's printout of one matrix (what an emulated anchor 1 writes).

    Centimetres truncated toward zero (C's ``(int)``), msb/lsb stored as uint8 (wraps).
    """
    out = []
    for i in range(N_DEVICES):
        tokens = []
        for j in range(N_DEVICES):
            mean, std = (mean_m[i, j], std_m[i, j]) if i != j else (0.0, 0.0)
            tokens += [*_c_split(mean), *_c_split(std)]
        out.append(("" if i == 0 else " ") + "".join(f"{t} , " for t in tokens) + "\r\n")
    return ("".join(out) + " \r\n Waiting for Start order\r\n").encode()


def _c_split(value_m: float) -> tuple[int, int]:
    """The firmware's ``msb = (int)(v*100/256)``, ``lsb = (int)(v*100) % 256`` in C (truncating
    division and remainder), stored into uint8."""
    cm = int(value_m * 100)  # int() truncates toward zero like C's cast
    msb = int(value_m * 100 / 256)
    lsb = cm - int(cm / 256) * 256  # C's % keeps the sign of the dividend
    return msb & 0xFF, lsb & 0xFF


class TiersDecoder:
    """Incremental decoder: ``feed(bytes)`` returns the messages completed by those bytes."""

    def __init__(self) -> None:
        self._buffer = b""
        self._rows: list[np.ndarray] = []

    def feed(self, data: bytes) -> list:
        self._buffer += data
        *lines, self._buffer = self._buffer.split(b"\n")
        messages = []
        for raw in lines:
            messages.extend(self._line(raw.decode("ascii", errors="replace").replace("\r", "")))
        return messages

    def _line(self, line: str) -> list:
        text = line.strip()
        if not text:
            return []
        if _ROWISH.match(text):
            try:
                self._rows.append(parse_row(text))
            except ParseError as err:
                self._rows = []
                return [RejectedMatrix(str(err))]
            if len(self._rows) == N_DEVICES:
                mean, std = decode_cells(np.stack(self._rows))
                self._rows = []
                return [RangeMatrixMessage(mean, std)]
            return []
        out = []
        if self._rows:  # a non-row line interrupted a matrix: it lost rows
            out.append(RejectedMatrix(f"matrix interrupted after {len(self._rows)} of {N_DEVICES} rows"))
            self._rows = []
        if text.startswith("Singled Sided Two Way Ranging"):
            out.append(Banner(text))
        elif text == ROLE_SWAP:
            out.append(RoleSwap())
        elif text == WAITING:
            out.append(WaitingForStart())
        else:
            out.append(OtherLine(text))
        return out
