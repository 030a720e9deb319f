"""Typed errors of the hardware layer; every message names the port (or the offending bytes)."""

from __future__ import annotations


class HardwareError(RuntimeError):
    """Base class for device and transport failures."""


class PortError(HardwareError):
    """A serial port could not be opened, or disappeared (USB unplug)."""

    def __init__(self, port: str, reason: str):
        super().__init__(f"port {port!r}: {reason}")
        self.port = port


class DeviceTimeout(HardwareError):
    """A device did not answer in time (e.g. a TIERS round hanging on a missing anchor)."""

    def __init__(self, port: str, what: str, timeout_s: float):
        super().__init__(f"port {port!r}: no {what} within {timeout_s:.2f} s")
        self.port, self.what, self.timeout_s = port, what, timeout_s


class ParseError(ValueError):
    """Bytes that do not follow a documented DWM1001 format. The only error parsers raise."""

    def __init__(self, what: str, data: bytes | str):
        shown = data if isinstance(data, str) else data[:80].hex(" ")
        super().__init__(f"{what}: {shown!r}")
        self.data = data
