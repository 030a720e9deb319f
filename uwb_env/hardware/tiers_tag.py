"""Codec of the TIERS *localization* tag firmware, pure bytes in, messages out.

``TIERS/dwm1001-uwb-firmware:Localization/Initiator/ss_init_main.c`` (the tag, ID 0) polls
anchors 1..4 in turn, 5 SS-TWR exchanges each, and after the fourth prints **one line**: for
each anchor ten ``%d`` bytes ::

    tag_id, anchor_id, mean_msb, mean_lsb, std_msb, std_lsb, b6, b7, b8, b9

comma-separated, no comma after the very last value, then ``\\r\\n``. Mean and std are in
centimetres (``msb = (int)(v*100/256)``, ``lsb = (int)(v*100) % 256``, stored as uint8, so a
negative mean wraps), the std is the population std. An anchor that did not answer 25 polls in
a row gets 255 in its four mean/std bytes (65535 cm: no real range). Bytes 6..9 are copied
from the reply buffer (``rx_buffer[18..21]``), which the matching Responders build never fills
with a position: they carry no information and are ignored.

A firmware quirk a host must know: the running sum behind the mean is reset only after a
*successful* anchor; when an anchor times out after answering some polls, its partial sum
leaks into the next anchor's mean (too long, with a std about as large as the error, because
the std is computed around that wrong mean). :meth:`TiersTagLine.plausible` therefore rejects
ranges whose std is implausibly large; the driver counts them.

Host -> tag (``main.c``): the single byte ``S`` starts polling (latched: the tag keeps polling,
one exchange per main-loop iteration, while the last byte read is ``S``); ``F`` prints ``END``
and stops the tag until a reset. After power-up the tag prints ``Singled Sided Two Way Ranging
INIT`` and waits for ``S``. A poll that gets no answer waits for the 66.7 ms RX timeout.

The responders answer only frames of the TIERS builds (preamble code 10, their own frame
layout): a stock-PANS tag cannot range to them, nor a TIERS tag to PANS anchors.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from uwb_env.hardware.errors import ParseError

N_ANCHORS = 4  # NUM_ANCHORS, a compile-time constant of the tag build
FIELDS_PER_ANCHOR = 10
NO_ANSWER = 255  # the four mean/std bytes of an anchor that timed out
_LINE = re.compile(rf"^\d{{1,3}}(?:,\d{{1,3}}){{{N_ANCHORS * FIELDS_PER_ANCHOR - 1}}}$")


@dataclass(frozen=True)
class TiersTagLine:
    """One line of a TIERS tag: per anchor (IDs 1..4, in order) the mean and std in metres;
    NaN where the anchor did not answer."""

    tag_id: int
    anchor_ids: tuple[int, ...]
    mean_m: np.ndarray
    std_m: np.ndarray

    def __eq__(self, other):
        return (isinstance(other, TiersTagLine) and self.tag_id == other.tag_id
                and self.anchor_ids == other.anchor_ids
                and np.array_equal(self.mean_m, other.mean_m, equal_nan=True)
                and np.array_equal(self.std_m, other.std_m, equal_nan=True))

    @property
    def answered(self) -> np.ndarray:
        return np.isfinite(self.mean_m)

    def plausible(self, max_std_m: float) -> np.ndarray:
        """Answered and with a std below ``max_std_m`` (5 LOS exchanges spread by a few cm; a
        partial sum leaked from a timed-out anchor, or a damaged byte, spreads far more)."""
        return self.answered & (self.std_m <= max_std_m)


@dataclass(frozen=True)
class RejectedTagLine:
    """A line that is not the firmware's format (dropped or inserted characters): never misread."""

    reason: str


@dataclass(frozen=True)
class OtherTagLine:
    text: str


def parse_tag_line(line: str) -> TiersTagLine:
    """40 uint8 values of one tag line -> :class:`TiersTagLine`; :class:`ParseError` otherwise."""
    text = line.strip()
    if not _LINE.match(text):
        raise ParseError(f"TIERS tag line: expected {N_ANCHORS * FIELDS_PER_ANCHOR} comma-separated integers", text)
    values = np.array([int(tok) for tok in text.split(",")], dtype=np.int64).reshape(N_ANCHORS, FIELDS_PER_ANCHOR)
    if values.max() > 255:
        raise ParseError("TIERS tag line: value above 255", text)
    tag_ids = set(values[:, 0].tolist())
    anchor_ids = tuple(int(a) for a in values[:, 1])
    # The firmware asks anchors 1..NUM_ANCHORS in turn and writes each row with its own ID: any
    # other ID (or two tag IDs in one line) is a damaged line that happens to parse.
    if len(tag_ids) != 1 or anchor_ids != tuple(range(1, N_ANCHORS + 1)):
        raise ParseError("TIERS tag line: tag/anchor ID columns are not one tag and anchors 1..4", text)
    cells = values[:, 2:6]
    silent = (cells == NO_ANSWER).all(axis=1)
    mean = (cells[:, 0] * 256 + cells[:, 1]) / 100.0
    std = (cells[:, 2] * 256 + cells[:, 3]) / 100.0
    mean[silent], std[silent] = np.nan, np.nan
    return TiersTagLine(int(values[0, 0]), anchor_ids, mean, std)


def encode_tag_line(mean_m, std_m, tag_id: int = 0, extra=(0, 0, 0, 0)) -> bytes:
    """The firmware's printout of one tag line (what an emulated TIERS tag writes): NaN mean ->
    the 255 no-answer bytes; centimetres truncated like C's ``(int)``, stored as uint8."""
    from uwb_env.hardware.tiers import _c_split

    values = []
    for j in range(N_ANCHORS):
        if not np.isfinite(mean_m[j]):
            cells = [NO_ANSWER] * 4
        else:
            cells = [*_c_split(float(mean_m[j])), *_c_split(float(std_m[j]))]
        values += [tag_id & 0xFF, j + 1, *cells, *(int(b) & 0xFF for b in extra)]
    return (",".join(str(v) for v in values) + "\r\n").encode()


class TiersTagDecoder:
    """Incremental decoder: ``feed(bytes)`` returns the lines completed by those bytes; never raises."""

    def __init__(self) -> None:
        self._buffer = b""

    def feed(self, data: bytes) -> list:
        self._buffer += data
        *lines, self._buffer = self._buffer.split(b"\n")
        out = []
        for raw in lines:
            text = raw.decode("ascii", errors="replace").replace("\r", "").strip()
            if not text:
                continue
            if re.fullmatch(r"[\d,\s]+", text):
                try:
                    out.append(parse_tag_line(text))
                except ParseError as err:
                    out.append(RejectedTagLine(str(err)))
            else:
                out.append(OtherTagLine(text))
        if len(self._buffer) > 4096:  # no line ending in 4 kB: garbage, start over
            self._buffer = b""
        return out
