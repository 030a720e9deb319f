"""Codec of the PANS binary TLV ("generic") API: ``type | length | value``, little-endian.

Every response starts with the return value ``40 01 err``. Positions are int32 millimetres
plus a uint8 quality factor. Responses are walked TLV by TLV (never at fixed offsets).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from uwb_env.hardware.errors import ParseError

POS_SET, POS_GET, UPD_RATE_SET, UPD_RATE_GET, CFG_GET, LOC_GET = 0x01, 0x02, 0x03, 0x04, 0x08, 0x0C
RET_VAL, POS_XYZ, UPD_RATE, CFG, RNG_AN_DIST, RNG_AN_POS_DIST = 0x40, 0x41, 0x45, 0x46, 0x48, 0x49
ERRORS = {0: "ok", 1: "unknown command or broken TLV frame", 2: "internal error", 3: "invalid parameter",
          4: "busy", 5: "operation not permitted"}


@dataclass(frozen=True)
class Position:
    x_m: float
    y_m: float
    z_m: float
    quality: int

    @classmethod
    def unpack(cls, data: bytes) -> Position:
        if len(data) != 13:
            raise ParseError("TLV position: expected 13 bytes", data)
        x, y, z, qf = struct.unpack("<iiiB", data)
        return cls(x / 1000.0, y / 1000.0, z / 1000.0, qf)

    def pack(self) -> bytes:
        return struct.pack("<iiiB", round(self.x_m * 1000), round(self.y_m * 1000), round(self.z_m * 1000),
                           self.quality)


@dataclass(frozen=True)
class Distance:
    address: int
    distance_m: float
    quality: int
    anchor_position: Position | None = None  # present in a tag's report


@dataclass(frozen=True)
class Response:
    """A decoded response: the return code and the other TLVs by type."""

    error: int
    tlvs: dict[int, bytes]

    @property
    def ok(self) -> bool:
        return self.error == 0


@dataclass(frozen=True)
class Location:
    position: Position | None
    distances: tuple[Distance, ...]
    node: str  # "tag" (0x49) or "anchor" (0x48)


def encode(type_: int, value: bytes = b"") -> bytes:
    if len(value) > 253:
        raise ValueError(f"value: {len(value)} bytes, at most 253")
    return bytes([type_, len(value)]) + value


def request_upd_rate_set(update_rate_100ms: int, stationary_100ms: int) -> bytes:
    return encode(UPD_RATE_SET, struct.pack("<HH", update_rate_100ms, stationary_100ms))


def split_tlvs(data: bytes) -> list[tuple[int, bytes]]:
    out, i = [], 0
    while i < len(data):
        if i + 2 > len(data):
            raise ParseError("TLV: truncated header", data)
        t, n = data[i], data[i + 1]
        if i + 2 + n > len(data):
            raise ParseError("TLV: value shorter than its length", data)
        out.append((t, bytes(data[i + 2:i + 2 + n])))
        i += 2 + n
    return out


def parse_response(data: bytes) -> Response:
    tlvs = split_tlvs(data)
    if not tlvs or tlvs[0][0] != RET_VAL or len(tlvs[0][1]) != 1:
        raise ParseError("TLV response: must start with 40 01 <err>", data)
    return Response(tlvs[0][1][0], {t: v for t, v in tlvs[1:]})


def response_length(buffer: bytes) -> int | None:
    """Length of the complete response at the start of ``buffer`` (None: need more bytes).

    A response is the ``40 01 err`` TLV and every TLV after it up to the next ``40`` type byte
    or the end of what has arrived; callers wait for the TLVs their request expects.
    """
    if len(buffer) < 3:
        return None
    if buffer[0] != RET_VAL or buffer[1] != 1:
        raise ParseError("TLV response: must start with 40 01 <err>", buffer)
    i = 3
    while i < len(buffer) and buffer[i] != RET_VAL:
        if i + 2 > len(buffer) or i + 2 + buffer[i + 1] > len(buffer):
            return None
        i += 2 + buffer[i + 1]
    return i


# loc_get: a tag without a position fix answers with its distance records only
EXPECTED = {POS_GET: (POS_XYZ,), UPD_RATE_GET: (UPD_RATE,), CFG_GET: (CFG,), LOC_GET: ()}


def decode_position(resp: Response) -> Position:
    _require(resp, POS_XYZ)
    return Position.unpack(resp.tlvs[POS_XYZ])


def decode_update_rate(resp: Response) -> tuple[int, int]:
    """(update rate, stationary update rate) in units of 100 ms."""
    value = _require(resp, UPD_RATE)
    if len(value) != 4:
        raise ParseError("update rate: expected 4 bytes", value)
    return struct.unpack("<HH", value)


def decode_cfg(resp: Response) -> dict:
    value = _require(resp, CFG)
    if len(value) != 2:
        raise ParseError("cfg: expected 2 bytes", value)
    b0, b1 = value
    return {"low_power": bool(b0 & 0x80), "loc_engine": bool(b0 & 0x40), "enc": bool(b0 & 0x20),
            "led": bool(b0 & 0x10), "ble": bool(b0 & 0x08), "fw_update": bool(b0 & 0x04),
            "uwb_mode": ("off", "passive", "active", "?")[b0 & 0x03], "mode": "anchor" if b1 & 0x20 else "tag",
            "initiator": bool(b1 & 0x10), "bridge": bool(b1 & 0x08), "stationary": bool(b1 & 0x04),
            "meas_mode": b1 & 0x03}


def decode_location(resp: Response) -> Location:
    if not resp.ok:
        raise ParseError(f"loc_get: error {resp.error} ({ERRORS.get(resp.error, '?')})", bytes([resp.error]))
    pos = Position.unpack(resp.tlvs[POS_XYZ]) if POS_XYZ in resp.tlvs else None
    if RNG_AN_POS_DIST in resp.tlvs:
        value, node, size = resp.tlvs[RNG_AN_POS_DIST], "tag", 20
    elif RNG_AN_DIST in resp.tlvs:
        value, node, size = resp.tlvs[RNG_AN_DIST], "anchor", 13
    else:
        return Location(pos, (), "tag")
    if not value or len(value) != 1 + size * value[0]:
        raise ParseError(f"loc_get distances: count does not match length ({node})", value)
    out = []
    for k in range(value[0]):
        item = value[1 + size * k: 1 + size * (k + 1)]
        if node == "tag":
            addr, dist, qf = struct.unpack("<HIB", item[:7])
            out.append(Distance(addr, dist / 1000.0, qf, Position.unpack(item[7:])))
        else:
            addr, dist, qf = struct.unpack("<QIB", item)
            out.append(Distance(addr, dist / 1000.0, qf))
    return Location(pos, tuple(out), node)


def encode_location_tag(position: Position | None, distances: list[Distance]) -> bytes:
    """The response a tag gives to ``dwm_loc_get`` (what the emulator sends)."""
    body = encode(RET_VAL, b"\x00") + (encode(POS_XYZ, position.pack()) if position else b"")
    items = b"".join(struct.pack("<HIB", d.address & 0xFFFF, round(d.distance_m * 1000), d.quality)
                     + d.anchor_position.pack() for d in distances)
    return body + encode(RNG_AN_POS_DIST, bytes([len(distances)]) + items)


def encode_location_anchor(position: Position, distances: list[Distance]) -> bytes:
    items = b"".join(struct.pack("<QIB", d.address, round(d.distance_m * 1000), d.quality) for d in distances)
    return encode(RET_VAL, b"\x00") + encode(POS_XYZ, position.pack()) + encode(
        RNG_AN_DIST, bytes([len(distances)]) + items)


def _require(resp: Response, type_: int) -> bytes:
    if not resp.ok:
        raise ParseError(f"TLV: error {resp.error} ({ERRORS.get(resp.error, '?')})", bytes([resp.error]))
    if type_ not in resp.tlvs:
        raise ParseError(f"TLV: response lacks type 0x{type_:02x}", b"".join(resp.tlvs.values()))
    return resp.tlvs[type_]
