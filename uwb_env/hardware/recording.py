"""Session recording (JSON lines, flushed per record) and replay through the same parsers.

Each line: ``{"t": seconds since the session began, "port": url, "dir": "rx"|"tx"|"event",
"hex": bytes as hex}`` (or ``"event"``/``"detail"`` for connection events). A crash loses at
most the record being written. :class:`ReplayTransport` serves a port's recorded ``rx`` bytes
through the transport interface, so the drivers and decoders run unchanged on a recording.
"""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

from uwb_env.hardware.errors import DeviceTimeout


class SessionRecorder:
    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.path, "a", buffering=1)  # line-buffered; we flush explicitly too
        self._lock = threading.Lock()
        self._t0 = time.monotonic()

    def _write(self, record: dict) -> None:
        record = {"t": round(time.monotonic() - self._t0, 6), **record}
        with self._lock:
            self._file.write(json.dumps(record) + "\n")
            self._file.flush()

    def record(self, port: str, direction: str, data: bytes) -> None:
        self._write({"port": port, "dir": direction, "hex": data.hex()})

    def event(self, port: str, event: str, detail: str = "") -> None:
        self._write({"port": port, "dir": "event", "event": event, "detail": detail})

    def close(self) -> None:
        with self._lock:
            self._file.close()


def read_session(path: str | Path) -> list[dict]:
    """All records; a last line cut by a crash is skipped."""
    out = []
    with open(path) as f:
        for line in f:
            try:
                out.append(json.loads(line))
            except json.JSONDecodeError:
                continue
    return out


class ReplayTransport:
    """The recorded ``rx`` bytes of ``port``, in order, behind the transport's read interface.

    Writes are checked against the recording's ``tx`` bytes when ``strict`` (a replay that
    diverges from the session raises instead of silently producing other data).
    """

    def __init__(self, path: str | Path, port: str, strict: bool = False):
        records = [r for r in read_session(path) if r.get("port") == port]
        self.url = f"replay:{port}"
        self._rx = bytearray(b"".join(bytes.fromhex(r["hex"]) for r in records if r["dir"] == "rx"))
        self._tx = b"".join(bytes.fromhex(r["hex"]) for r in records if r["dir"] == "tx")
        self._tx_pos = 0
        self.strict = strict
        self.reconnections = sum(1 for r in records if r.get("event") == "reconnected")
        self.recorder = None

    def write(self, data: bytes, pace_s: float = 0.0) -> None:
        if self.strict:
            expected = self._tx[self._tx_pos:self._tx_pos + len(data)]
            if expected != data:
                raise ValueError(f"replay {self.url}: wrote {data!r}, the session wrote {expected!r}")
        self._tx_pos += len(data)

    def read_available(self) -> bytes:
        data = bytes(self._rx)
        self._rx.clear()
        return data

    def wait_for(self, predicate, timeout_s: float, what: str) -> bytes:
        end = predicate(bytes(self._rx))
        if end is None:
            raise DeviceTimeout(self.url, what, timeout_s)
        data = bytes(self._rx[:end])
        del self._rx[:end]
        return data

    def read_until(self, token: bytes, timeout_s: float) -> bytes:
        return self.wait_for(lambda b: b.find(token) + len(token) if token in b else None, timeout_s, repr(token))

    def flush_input(self) -> None:
        pass  # a replay has no stale bytes: everything recorded was read by the session

    def close(self) -> None:
        pass
