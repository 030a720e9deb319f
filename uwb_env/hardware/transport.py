"""Serial transport: pyserial ports by URL, a background reader, reconnect with backoff.

Ports open with ``serial.serial_for_url`` so ``/dev/ttyACM0``, ``loop://``, ``socket://host:port``
and ``rfc2217://`` work alike; 115200 8N1 with a read timeout always set; ``exclusive=True``
where the port type supports it. A background thread moves bytes into our own buffer (the
OS buffer of a USB CDC port is small); when the port disappears (USB unplug raises
``SerialException``) it reconnects with exponential backoff and counts the reconnections.
Every byte in either direction goes to an optional recorder first (flushed as it arrives).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import serial

from uwb_env.hardware.errors import DeviceTimeout, PortError

BAUDRATE = 115200
READ_TIMEOUT_S = 0.05


def open_port(url: str, baudrate: int = BAUDRATE, timeout_s: float = READ_TIMEOUT_S) -> serial.SerialBase:
    """Open ``url`` 8N1 with a read timeout; exclusive access where supported."""
    kwargs = dict(baudrate=baudrate, bytesize=serial.EIGHTBITS, parity=serial.PARITY_NONE,
                  stopbits=serial.STOPBITS_ONE, timeout=timeout_s, write_timeout=1.0)
    try:
        try:
            return serial.serial_for_url(url, exclusive=True, **kwargs)
        except (TypeError, ValueError):  # URL handlers without the exclusive option (loop://, socket://)
            return serial.serial_for_url(url, **kwargs)
    except (serial.SerialException, OSError) as err:
        raise PortError(url, f"cannot open: {err}") from err


class SerialTransport:
    """A port with a background reader. Thread-safe ``write``; ``read_until`` on our buffer."""

    def __init__(self, url: str, *, recorder=None, baudrate: int = BAUDRATE, reconnect: bool = True,
                 backoff_s: tuple[float, float] = (0.05, 2.0), opener: Callable[[str], object] | None = None):
        self.url = url
        self.recorder = recorder
        self.reconnect = reconnect
        self.backoff_s = backoff_s
        self._opener = opener or (lambda u: open_port(u, baudrate))
        self._buffer = bytearray()
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self.connected = threading.Event()
        self.reconnections = 0
        self.last_error: str | None = None
        self._port = self._opener(url)
        self.connected.set()
        self._thread = threading.Thread(target=self._reader, name=f"uwb-reader {url}", daemon=True)
        self._thread.start()

    # -- I/O -------------------------------------------------------------------------------------
    def write(self, data: bytes, pace_s: float = 0.0, wait_s: float | None = None) -> None:
        """Write ``data`` (byte by byte with ``pace_s`` between bytes when > 0, for shells
        that drop fast typing). While the port is away, wait up to ``wait_s`` (default: two
        reconnection backoffs) for it to return, then raise :class:`PortError`."""
        if not self.connected.wait(timeout=2 * self.backoff_s[1] if wait_s is None else wait_s):
            raise PortError(self.url, f"not connected ({self.last_error})")
        if self.recorder is not None:
            self.recorder.record(self.url, "tx", data)
        try:
            if pace_s > 0:
                for b in data:
                    self._port.write(bytes([b]))
                    time.sleep(pace_s)
            else:
                self._port.write(data)
            self._port.flush()
        except (serial.SerialException, OSError) as err:
            self._lost(err)
            raise PortError(self.url, f"write failed: {err}") from err

    def read_available(self) -> bytes:
        with self._cond:
            data = bytes(self._buffer)
            self._buffer.clear()
        return data

    def wait_for(self, predicate: Callable[[bytes], int | None], timeout_s: float, what: str) -> bytes:
        """Wait until ``predicate(buffer)`` returns an end index; consume and return that prefix.

        Raises :class:`DeviceTimeout` (naming the port and ``what``) when it does not happen.
        """
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while True:
                end = predicate(bytes(self._buffer))
                if end is not None:
                    data = bytes(self._buffer[:end])
                    del self._buffer[:end]
                    return data
                left = deadline - time.monotonic()
                if left <= 0:
                    raise DeviceTimeout(self.url, what, timeout_s)
                self._cond.wait(min(left, 0.05))

    def read_until(self, token: bytes, timeout_s: float) -> bytes:
        return self.wait_for(lambda b: b.find(token) + len(token) if token in b else None, timeout_s,
                             f"{token!r}")

    def flush_input(self) -> None:
        with self._cond:
            self._buffer.clear()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=1.0)
        try:
            self._port.close()
        except (serial.SerialException, OSError):
            pass

    def __enter__(self) -> SerialTransport:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- background ------------------------------------------------------------------------------
    def _reader(self) -> None:
        while not self._stop.is_set():
            if not self.connected.is_set():
                self._reconnect()
                continue
            try:
                data = self._port.read(max(1, self._port.in_waiting))
            except (serial.SerialException, OSError, TypeError, AttributeError) as err:
                # TypeError/AttributeError: pyserial's posix port after its fd vanished mid-read
                self._lost(err)
                continue
            if data:
                if self.recorder is not None:
                    self.recorder.record(self.url, "rx", data)
                with self._cond:
                    self._buffer += data
                    self._cond.notify_all()

    def _lost(self, err: Exception) -> None:
        if not self.connected.is_set():
            return
        self.connected.clear()
        self.last_error = f"{type(err).__name__}: {err}"
        if self.recorder is not None:
            self.recorder.event(self.url, "disconnected", self.last_error)
        try:
            self._port.close()
        except (serial.SerialException, OSError):
            pass
        if not self.reconnect:
            self._stop.set()

    def _reconnect(self) -> None:
        delay = self.backoff_s[0]
        while not self._stop.is_set():
            try:
                self._port = self._opener(self.url)
            except PortError as err:
                self.last_error = str(err)
                self._stop.wait(delay)
                delay = min(2 * delay, self.backoff_s[1])
                continue
            self.reconnections += 1
            if self.recorder is not None:
                self.recorder.event(self.url, "reconnected", f"attempt {self.reconnections}")
            self.connected.set()
            return
