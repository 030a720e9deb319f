"""Codec of the stock PANS firmware's shell mode, pure bytes in, messages out.

Enter the shell with two ``\\r`` (prompt ``dwm> ``); ``lec``/``les``/``lep`` toggle streams of
CSV/text reports (metres, 2 decimals). Field quirks handled here: the echo and the prompt can
be glued to the first data line (reports are found anywhere in a line), ``AN`` groups can be
duplicated or truncated at high rates (each group is validated, duplicates dropped, the
announced count is not trusted), and a command sent in generic mode answers ``@\\x01\\x01``.
"""

from __future__ import annotations

import operator
import re
from dataclasses import dataclass
from typing import NamedTuple

from uwb_env.hardware.errors import ParseError

PROMPT = b"dwm> "
ENTER_SHELL = b"\r\r"
GENERIC_ERROR = b"@\x01\x01"
_NUM = r"-?\d+(?:\.\d+)?"
_AN = re.compile(rf"AN(\d+),([0-9A-Fa-f]{{4}}),({_NUM}),({_NUM}),({_NUM}),({_NUM})(?=,AN|,POS|\s*$)")
_POS = re.compile(rf"POS,({_NUM}),({_NUM}),({_NUM}),(\d+)\s*$")
_DIST = re.compile(r"DIST,(\d+)")
_LES = re.compile(rf"([0-9A-Fa-f]{{4}})\[({_NUM}),({_NUM}),({_NUM})(?:,\d+)?\]=({_NUM})")
_EST = re.compile(rf"est\[({_NUM}),({_NUM}),({_NUM}),(\d+)\]")


class AnchorRange(NamedTuple):
    """One anchor seen by a tag: its 16-bit ID (hex), position and distance (m)."""

    anchor_id: str
    position_m: tuple[float, float, float]
    distance_m: float


class LocationReport(NamedTuple):
    """A ``lec``/``les`` line (ranges, optional position) or a ``lep`` line (position only)."""

    ranges: tuple[AnchorRange, ...]
    position_m: tuple[float, float, float] | None
    quality: int | None
    kind: str  # "lec", "les" or "lep"


@dataclass(frozen=True)
class Prompt:
    pass


@dataclass(frozen=True)
class GenericModeError:
    """``@\\x01\\x01``: the device is in generic (TLV) mode and did not understand text."""


@dataclass(frozen=True)
class TextLine:
    text: str


_FLOAT = r"(-?\d+(?:\.\d+)?)"
_LEC_BY_COUNT: dict[int, tuple[re.Pattern, operator.itemgetter]] = {}


def _lec_pattern(n: int) -> tuple[re.Pattern, operator.itemgetter]:
    # One compiled pattern per anchor count matches a whole well-formed line in C; the getter
    # picks its numeric groups (every group but the IDs).
    if n not in _LEC_BY_COUNT:
        groups = "".join(f",AN{i},([0-9A-Fa-f]{{4}}),{_FLOAT},{_FLOAT},{_FLOAT},{_FLOAT}" for i in range(n))
        pattern = re.compile(rf"DIST,{n}{groups}(?:,POS,{_FLOAT},{_FLOAT},{_FLOAT},(\d+))?\s*")
        _LEC_BY_COUNT[n] = pattern, operator.itemgetter(*[j for j in range(5 * n) if j % 5], 5 * n)
    return _LEC_BY_COUNT[n]


def _lec_fast(body: str) -> LocationReport | None:
    """A well-formed line in one regex match (the common case); None sends it to the group-by-group path."""
    comma = body.find(",", 5)
    count = body[5:comma]
    if not count.isdigit() or int(count) > 15:
        return None
    n = int(count)
    if n == 0:
        return None
    pattern, numeric = _lec_pattern(n)
    m = pattern.fullmatch(body)
    if m is None:
        return None
    g = m.groups()
    ids = g[0:5 * n:5]
    if len(set(ids)) != n:
        return None
    v = list(map(float, numeric(g)[:-1]))
    ranges = tuple(AnchorRange(ids[i].upper(), (v[4 * i], v[4 * i + 1], v[4 * i + 2]), v[4 * i + 3])
                   for i in range(n))
    if g[5 * n] is None:
        return LocationReport(ranges, None, None, "lec")
    return LocationReport(ranges, (float(g[5 * n]), float(g[5 * n + 1]), float(g[5 * n + 2])), int(g[5 * n + 3]),
                          "lec")


def parse_lec(line: str) -> LocationReport:
    """A ``DIST,n,AN0,...`` line (anywhere in ``line``) -> its valid anchor groups and position."""
    start = line.find("DIST,")
    if start < 0:
        raise ParseError("lec line: no 'DIST,'", line)
    body = line[start:]
    fast = _lec_fast(body)
    if fast is not None:
        return fast
    if not _DIST.match(body):
        raise ParseError("lec line: bad DIST count", line)
    seen: dict[str, AnchorRange] = {}
    for m in _AN.finditer(body):
        anchor = m.group(2).upper()
        if anchor not in seen:  # duplicated groups from corrupted reports: keep the first
            x, y, z, d = (float(v) for v in m.group(3, 4, 5, 6))
            seen[anchor] = AnchorRange(anchor, (x, y, z), d)
    pos = _POS.search(body)
    if not seen and not pos:
        raise ParseError("lec line: no valid AN group or POS", line)
    position = tuple(float(v) for v in pos.group(1, 2, 3)) if pos else None
    return LocationReport(tuple(seen.values()), position, int(pos.group(4)) if pos else None, "lec")


def parse_lep(line: str) -> LocationReport:
    m = _POS.search(line[line.find("POS,"):] if "POS," in line else "")
    if not m:
        raise ParseError("lep line: expected POS,x,y,z,qf", line)
    return LocationReport((), tuple(float(v) for v in m.group(1, 2, 3)), int(m.group(4)), "lep")


def parse_les(line: str) -> LocationReport:
    ranges = {}
    for m in _LES.finditer(line):
        anchor = m.group(1).upper()
        ranges.setdefault(anchor, AnchorRange(anchor, tuple(float(v) for v in m.group(2, 3, 4)), float(m.group(5))))
    if not ranges:
        raise ParseError("les line: no ID[x,y,z]=d group", line)
    est = _EST.search(line)
    position = tuple(float(v) for v in est.group(1, 2, 3)) if est else None
    return LocationReport(tuple(ranges.values()), position, int(est.group(4)) if est else None, "les")


def format_lec(ranges: list[AnchorRange], position_m=None, quality: int | None = None) -> str:
    """The firmware's ``lec`` line (without CRLF), as an emulated tag prints it."""
    parts = [f"DIST,{len(ranges)}"]
    for i, r in enumerate(ranges):
        x, y, z = r.position_m
        parts.append(f"AN{i},{r.anchor_id},{x:.2f},{y:.2f},{z:.2f},{r.distance_m:.2f}")
    if position_m is not None:
        parts.append(f"POS,{position_m[0]:.2f},{position_m[1]:.2f},{position_m[2]:.2f},{quality}")
    return ",".join(parts)


class ShellDecoder:
    """Incremental decoder of shell output: reports, prompts, the generic-mode error, text."""

    def __init__(self) -> None:
        self._buffer = b""

    def feed(self, data: bytes) -> list:
        *lines, rest = (self._buffer + data).split(b"\n")
        out = []
        for line in lines:
            if PROMPT in line or GENERIC_ERROR in line:
                self._buffer = line + b"\n"
                out.extend(self._tokens())
            else:
                out.extend(self._chunk(line.decode("ascii", errors="replace").replace("\r", "")))
        self._buffer = rest
        if PROMPT in rest or GENERIC_ERROR in rest:
            out.extend(self._tokens())
        return out

    def _tokens(self) -> list:
        """Split the buffer at newlines, prompts and generic-mode errors (prompts have no
        newline after them); what follows the last token stays buffered."""
        out = []
        while True:
            # The prompt has no newline: it ends a chunk on its own.
            cut = [(i, n) for i, n in ((self._buffer.find(b"\n"), 1), (self._buffer.find(PROMPT), len(PROMPT)),
                                       (self._buffer.find(GENERIC_ERROR), len(GENERIC_ERROR))) if i >= 0]
            if not cut:
                break
            index, size = min(cut)
            chunk, token = self._buffer[:index], self._buffer[index:index + size]
            self._buffer = self._buffer[index + size:]
            out.extend(self._chunk(chunk.decode("ascii", errors="replace").replace("\r", "")))
            if token == PROMPT:
                out.append(Prompt())
            elif token == GENERIC_ERROR:
                out.append(GenericModeError())
        return out

    @staticmethod
    def _chunk(text: str) -> list:
        text = text.strip()
        if not text:
            return []
        try:
            if "DIST," in text:
                return [parse_lec(text)]
            if "POS," in text:
                return [parse_lep(text)]
            if "]=" in text:
                return [parse_les(text)]
        except ParseError:
            return [TextLine(text)]  # damaged report: reported as text, never misread
        return [TextLine(text)]
