"""Session recording (JSON lines, flushed per record) and replay through the same parsers.

Each line: ``{"t": seconds since the session began, "port": url, "dir": "rx"|"tx"|"event",
"hex": bytes as hex}`` (or ``"event"``/``"detail"`` for connection events). Each session
starts with a ``{"dir": "session", "started": ISO time}`` line, so several sessions appended to
one file stay apart (:func:`read_session` picks one, by default the last). A crash loses at
most the record being written: a torn last line is ended before the next session's first
record, never glued to it. :class:`ReplayTransport` serves a port's recorded ``rx`` bytes
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
        torn = self.path.is_file() and self.path.stat().st_size > 0 and not _ends_with_newline(self.path)
        self._file = open(self.path, "a", buffering=1)  # line-buffered; we flush explicitly too
        if torn:  # a crashed session's cut record: end it so it cannot swallow our first one
            self._file.write("\n")
        self._lock = threading.Lock()
        self._t0 = time.monotonic()
        self._file.write(json.dumps({"t": 0.0, "dir": "session", "started": time.strftime("%Y-%m-%dT%H:%M:%S")}) + "\n")
        self._file.flush()

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


def _ends_with_newline(path: Path) -> bool:
    with open(path, "rb") as f:
        f.seek(-1, 2)
        return f.read(1) == b"\n"


def read_sessions(path: str | Path) -> list[list[dict]]:
    """The file's sessions, in order, each a list of records (session headers left out); lines
    cut by a crash are skipped. Records before any header (older files) form a session."""
    sessions: list[list[dict]] = [[]]
    with open(path) as f:
        for line in f:
            try:
                record = json.loads(line)
            except json.JSONDecodeError:
                continue
            if record.get("dir") == "session":
                sessions.append([])
            else:
                sessions[-1].append(record)
    return [s for i, s in enumerate(sessions) if s or i > 0]


def read_session(path: str | Path, session: int = -1) -> list[dict]:
    """The records of one session (default: the last one written)."""
    sessions = read_sessions(path)
    if not sessions:
        return []
    try:
        return sessions[session]
    except IndexError:
        raise ValueError(f"session={session!r}: {path} holds {len(sessions)} session(s)") from None


class ReplayTransport:
    """The recorded ``rx`` bytes of ``port``, in order, behind the transport's read interface.

    Writes are checked against the recording's ``tx`` bytes when ``strict`` (a replay that
    diverges from the session raises instead of silently producing other data).
    """

    def __init__(self, path: str | Path, port: str, strict: bool = False, session: int = -1):
        records = [r for r in read_session(path, session) if r.get("port") == port]
        self.url = f"replay:{port}"
        self._rx = bytearray(b"".join(bytes.fromhex(r["hex"]) for r in records if r["dir"] == "rx"))
        self._tx = b"".join(bytes.fromhex(r["hex"]) for r in records if r["dir"] == "tx")
        self._tx_pos = 0
        self.strict = strict
        self.reconnections = sum(1 for r in records if r.get("event") == "reconnected")
        self.recorder = None

    def write(self, data: bytes, pace_s: float = 0.0, wait_s: float | None = None) -> None:
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
