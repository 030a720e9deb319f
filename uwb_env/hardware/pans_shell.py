"""Codec of the stock PANS firmware's shell mode, pure bytes in, messages out.

Enter the shell with two ``\\r`` (prompt ``dwm> ``); ``lec``/``les``/``lep`` toggle streams of
CSV/text reports (metres, 2 decimals). Field quirks handled here: the echo and the prompt can
be glued to the first data line (reports are found anywhere in a line), ``AN`` groups can be
duplicated or truncated at high rates (each group is validated, duplicates dropped, the
announced count is not trusted), and a command sent in generic mode answers ``@\\x01\\x01``.
"""

from __future__ import annotations

import math
import operator
import re
from dataclasses import dataclass
from typing import NamedTuple

from uwb_env.hardware.errors import ParseError

PROMPT = b"dwm> "
ENTER_SHELL = b"\r\r"
GENERIC_ERROR = b"@\x01\x01"
# The firmware prints metres with exactly two decimals ("%d.%02d"): a number in any other form
# lost or gained a character on the wire (a lost '.' turns 6.44 into 644, a lost digit into 6.4).
_NUM = r"-?\d+\.\d\d"
_STRICT = re.compile(_NUM)
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


_HEX = frozenset("0123456789abcdefABCDEF")
_COUNTS = {str(n): n for n in range(1, 16)}
_LEC_LAYOUT: dict[tuple[int, bool], tuple] = {}
# Anchor groups seen before -> (IDs, positions): anchors report their configured positions, so a
# stream repeats them and only distances (and the tag's position) need converting.
_ANCHOR_CACHE: dict[tuple, tuple] = {}
_ANCHOR_CACHE_SIZE = 4096


def _lec_layout(n: int, with_pos: bool) -> tuple:
    # Per (anchor count, POS present): C-level getters for the labels, the anchor fields
    # (ID, x, y, z of each), the distances and the tag position.
    key = (n, with_pos)
    if key not in _LEC_LAYOUT:
        pos_at = 2 + 6 * n
        starts = [2 + 6 * i for i in range(n)]
        labels = tuple(f"AN{i}" for i in range(n)) + (("POS",) if with_pos else ())
        get_labels = operator.itemgetter(*(starts + ([pos_at] if with_pos else [])))
        get_anchor = operator.itemgetter(*[k + j for k in starts for j in range(1, 5)])
        get_dist = operator.itemgetter(*[k + 5 for k in starts]) if n > 1 else (lambda f: (f[7],))
        get_pos = operator.itemgetter(pos_at + 1, pos_at + 2, pos_at + 3)
        _LEC_LAYOUT[key] = (labels if len(labels) > 1 else labels[0], get_labels, get_anchor, get_dist, get_pos)
    return _LEC_LAYOUT[key]


def _anchor_groups(fields: tuple, n: int) -> tuple | None:
    """Validate and convert the (ID, x, y, z) fields of n anchors; None if malformed."""
    ids = fields[0::4]
    joined = "".join(ids)
    if len(joined) != 4 * n or not _HEX.issuperset(joined) or len(set(ids)) != n:
        return None
    coords = [x for i, x in enumerate(fields) if i % 4]
    if not all(map(_STRICT.fullmatch, coords)):
        return None
    v = list(map(float, coords))
    if not math.isfinite(sum(v)):
        return None
    return tuple(i.upper() for i in ids), tuple((v[3 * k], v[3 * k + 1], v[3 * k + 2]) for k in range(n))


def _lec_fast(body: str) -> LocationReport | None:
    """A well-formed line by field positions (the common case); None sends it to the regexes."""
    f = body.rstrip().split(",")
    n = _COUNTS.get(f[1]) if len(f) > 1 else None
    if n is None:
        return None
    size = len(f) - 2 - 6 * n
    if size == 5:
        if not f[-1].isdigit():
            return None
    elif size != 0:
        return None
    labels, get_labels, get_anchor, get_dist, get_pos = _lec_layout(n, size == 5)
    if get_labels(f) != labels:
        return None
    fields = get_anchor(f)
    groups = _ANCHOR_CACHE.get(fields)
    if groups is None:
        groups = _anchor_groups(fields, n)
        if groups is None:
            return None
        if len(_ANCHOR_CACHE) >= _ANCHOR_CACHE_SIZE:
            _ANCHOR_CACHE.clear()
        _ANCHOR_CACHE[fields] = groups
    dist_fields = get_dist(f)
    pos_fields = get_pos(f) if size == 5 else ()
    if not all(map(_STRICT.fullmatch, dist_fields)) or not all(map(_STRICT.fullmatch, pos_fields)):
        return None  # a damaged number: the tolerant path keeps the intact groups
    d = list(map(float, dist_fields))
    pos = tuple(map(float, pos_fields)) if size == 5 else None
    if not math.isfinite(sum(d) + (sum(pos) if pos else 0.0)):
        return None
    new = tuple.__new__  # NamedTuple construction without its Python-level __new__ (hot path)
    ids, positions = groups
    ranges = tuple([new(AnchorRange, (ids[i], positions[i], d[i])) for i in range(n)])
    return new(LocationReport, (ranges, pos, int(f[-1]) if pos else None, "lec"))


def parse_lec(line: str) -> LocationReport:
    """A ``DIST,n,AN0,...`` line (anywhere in ``line``) -> its valid anchor groups and position."""
    start = line.find("DIST,")
    if start < 0:
        raise ParseError("lec line: no 'DIST,'", line)
    body = line[start:]
    fast = _lec_fast(body)
    return fast if fast is not None else _lec_by_groups(line, body)


def _lec_by_groups(line: str, body: str) -> LocationReport:
    """The tolerant path: every valid ``AN`` group anywhere, duplicates dropped."""
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
        buffer = self._buffer + data
        cut = buffer.rfind(b"\n")
        complete, rest = (buffer[:cut], buffer[cut + 1:]) if cut >= 0 else (b"", buffer)
        out = []
        if complete and PROMPT not in complete and GENERIC_ERROR not in complete:
            # the streaming case: decode once, then line by line
            chunk, fast, append = self._chunk, _lec_fast, out.append
            for line in complete.decode("ascii", errors="replace").replace("\r", "").split("\n"):
                report = fast(line) if line.startswith("DIST,") else None  # the common, clean case
                if report is not None:
                    append(report)
                else:
                    out.extend(chunk(line))
        elif complete:
            for line in complete.split(b"\n"):
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
