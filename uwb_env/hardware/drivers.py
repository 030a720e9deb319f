"""Device drivers over a transport: the TIERS autocalibration anchor and PANS tags.

Drivers own the protocol rules learned in the field (see ``docs`` and the codecs): the TIERS
start byte is ``S`` alone and a round that never ends is reported with the round number;
the PANS shell is entered with a retry loop and paced typing; TLV requests flush stale input
first and walk the answer by TLVs.
"""

from __future__ import annotations

import time

import numpy as np

from uwb_env.hardware import tlv
from uwb_env.hardware.errors import DeviceTimeout, HardwareError, ParseError
from uwb_env.hardware.pans_shell import PROMPT, GenericModeError, LocationReport, Prompt, ShellDecoder
from uwb_env.hardware.tiers import START, RangeMatrixMessage, RejectedMatrix, TiersDecoder


class RoundFailed(HardwareError):
    """A calibration round ended without a usable matrix (timeout or damaged rows)."""

    def __init__(self, port: str, round_number: int, reason: str):
        super().__init__(f"port {port!r}: calibration round {round_number} failed: {reason}")
        self.round_number, self.reason = round_number, reason


class TiersAnchorDriver:
    """Anchor ID 1 of the TIERS firmware: one ``S`` per round, one matrix back."""

    def __init__(self, transport, round_timeout_s: float = 4.0):
        self.transport = transport
        self.round_timeout_s = round_timeout_s
        self.decoder = TiersDecoder()
        self.rounds_started = 0
        self._deadline: float | None = None

    @property
    def running(self) -> bool:
        return self._deadline is not None

    def start_round(self) -> int:
        """Send the start byte (exactly ``S``: a line ending would abort the round)."""
        if self.running:
            raise HardwareError(f"port {self.transport.url!r}: round {self.rounds_started} still running")
        self.transport.flush_input()
        self.decoder = TiersDecoder()
        self.transport.write(START)
        self.rounds_started += 1
        self._deadline = time.monotonic() + self.round_timeout_s
        return self.rounds_started

    def poll(self) -> RangeMatrixMessage | None:
        """The round's matrix once it has arrived; None while it runs.

        Raises :class:`RoundFailed` when the round times out (a missing anchor hangs the
        firmware silently) or its matrix arrived damaged.
        """
        if not self.running:
            return None
        for message in self.decoder.feed(self.transport.read_available()):
            if isinstance(message, RangeMatrixMessage):
                self._deadline = None
                return message
            if isinstance(message, RejectedMatrix):
                self._deadline = None
                raise RoundFailed(self.transport.url, self.rounds_started, message.reason)
        if time.monotonic() > self._deadline:
            self._deadline = None
            raise RoundFailed(self.transport.url, self.rounds_started,
                              f"no matrix within {self.round_timeout_s:.1f} s (an anchor missing or hung?)")
        return None

    def run_round(self) -> RangeMatrixMessage:
        self.start_round()
        while True:
            message = self.poll()
            if message is not None:
                return message
            time.sleep(0.005)


class PansShellTagDriver:
    """A PANS tag in shell mode streaming ``lec`` reports."""

    def __init__(self, transport, pace_s: float = 0.0, retries: int = 5, prompt_timeout_s: float = 1.5):
        self.transport = transport
        self.pace_s, self.retries, self.prompt_timeout_s = pace_s, retries, prompt_timeout_s
        self.decoder = ShellDecoder()
        self.latest: LocationReport | None = None
        self.latest_time: float = -np.inf
        self.reports = 0

    def enter_shell(self) -> None:
        """Two ``\\r`` (spaced), wait for ``dwm> ``; retry when the device answers in generic mode."""
        for _ in range(self.retries):
            self.transport.flush_input()
            self.transport.write(b"\r")
            time.sleep(0.05)
            self.transport.write(b"\r")
            try:
                self.transport.read_until(PROMPT, self.prompt_timeout_s)
                return
            except DeviceTimeout:
                continue
        what = "PANS shell prompt after 2x Enter (the TIERS anchor firmware has no shell: anchor/tag ports swapped?)"
        raise DeviceTimeout(self.transport.url, what, self.prompt_timeout_s * self.retries)

    def command(self, text: str) -> None:
        self.transport.write(text.encode() + b"\r", pace_s=self.pace_s)

    def start_lec(self) -> None:
        self.enter_shell()
        self.command("lec")

    def poll(self) -> list[LocationReport]:
        """Reports that arrived since the last call (the newest is also kept in ``latest``)."""
        out = []
        for message in self.decoder.feed(self.transport.read_available()):
            if isinstance(message, LocationReport):
                out.append(message)
            elif isinstance(message, GenericModeError):
                self.start_lec()  # the device reset into generic mode: re-enter and restart
            elif isinstance(message, Prompt):
                continue
        if out:
            self.latest, self.latest_time = out[-1], time.monotonic()
            self.reports += len(out)
        return out


class PansTlvDriver:
    """Request/response over the binary TLV API."""

    def __init__(self, transport, timeout_s: float = 1.0):
        self.transport, self.timeout_s = transport, timeout_s

    def request(self, type_: int, value: bytes = b"") -> tlv.Response:
        self.transport.flush_input()
        self.transport.write(tlv.encode(type_, value))
        expected = tlv.EXPECTED.get(type_, ())

        def complete(buffer: bytes) -> int | None:
            try:
                end = tlv.response_length(buffer)
            except ParseError:
                return len(buffer)  # garbage: hand it to the parser, which names it
            if end is None:
                return None
            types = {t for t, _ in tlv.split_tlvs(buffer[3:end])}
            ok = buffer[2] == 0
            if ok and type_ == tlv.LOC_GET and not types & {tlv.RNG_AN_DIST, tlv.RNG_AN_POS_DIST}:
                return None
            return end if (not ok or set(expected) <= types) else None

        return tlv.parse_response(self.transport.wait_for(complete, self.timeout_s, f"TLV response to 0x{type_:02x}"))

    def loc_get(self) -> tlv.Location:
        return tlv.decode_location(self.request(tlv.LOC_GET))

    def pos_get(self) -> tlv.Position:
        return tlv.decode_position(self.request(tlv.POS_GET))

    def cfg_get(self) -> dict:
        return tlv.decode_cfg(self.request(tlv.CFG_GET))

    def update_rate_get(self) -> tuple[int, int]:
        return tlv.decode_update_rate(self.request(tlv.UPD_RATE_GET))

    def update_rate_set(self, rate_100ms: int, stationary_100ms: int) -> None:
        resp = self.request(tlv.UPD_RATE_SET, tlv.request_upd_rate_set(rate_100ms, stationary_100ms)[2:])
        if not resp.ok:
            raise HardwareError(f"port {self.transport.url!r}: update rate set: error {resp.error}")
