"""Device drivers over a transport: the TIERS autocalibration anchor, TIERS and PANS tags.

Drivers own the protocol rules learned in the field (see ``docs`` and the codecs): the TIERS
start byte is ``S`` alone and a round that never ends is reported with the round number;
the PANS shell is entered with a retry loop and paced typing; TLV requests flush stale input
first and walk the answer by TLVs.
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import replace

import numpy as np

from uwb_env.hardware import tlv
from uwb_env.hardware.errors import DeviceTimeout, HardwareError, ParseError, PortError
from uwb_env.hardware.pans_shell import PROMPT, AnchorRange, GenericModeError, LocationReport, ShellDecoder
from uwb_env.hardware.tiers import (
    BANNER_INIT,
    START,
    Banner,
    RangeMatrixMessage,
    RejectedMatrix,
    TiersDecoder,
    WaitingForStart,
    repeated_cells,
)
from uwb_env.hardware.tiers_tag import OtherTagLine, RejectedTagLine, TiersTagDecoder, TiersTagLine


class RoundFailed(HardwareError):
    """A calibration round ended without a usable matrix (timeout or damaged rows)."""

    def __init__(self, port: str, round_number: int, reason: str):
        super().__init__(f"port {port!r}: calibration round {round_number} failed: {reason}")
        self.round_number, self.reason = round_number, reason


class TiersAnchorDriver:
    """Anchor ID 1 of the TIERS firmware: one ``S`` per round, one matrix back, each matrix
    tied to the request that caused it.

    The firmware latches the start flag (an ``S`` sent while a round runs is absorbed by that
    round; there is no abort) and, after printing the matrix, sleeps ~30 ms and flushes its RX
    *and* TX FIFOs before printing ``Waiting for Start order`` (see
    ``Autocalibration/Initiator/main.c`` and ``ss_init_main.c`` in TIERS/dwm1001-uwb-firmware).
    So the driver is an explicit state machine:

    - ``READY``: the firmware waits for ``S`` (after ``Waiting for Start order``, the boot banner,
      or at connection). :meth:`start_round` sends ``S`` and enters ``RUNNING``.
    - ``RUNNING``: the next matrix belongs to this request. It moves to ``SETTLING`` (the
      firmware is about to flush; an ``S`` now would be lost).
    - ``SETTLING``: waiting for ``Waiting for Start order`` (or the banner) -> ``READY``.
    - ``DRAINING``: a request timed out or was abandoned while the firmware may still run it,
      or the boot banner arrived after its ``S`` without a power cycle of the port in between
      (a reboot after the ``S``, or one before it whose banner was still in flight: the ``S``
      may have started a round): a matrix that
      arrives now is stale (discarded, counted in ``stale_matrices``); ``READY`` again on
      ``Waiting for Start order`` or the banner, or after ``drain_quiet_s`` without a byte from
      the device (a hung round that will never print).

    A start requested while not ``READY`` is held and sent as soon as the firmware is ready;
    its timeout runs from the request, so a device that never becomes ready fails each round
    within its timeout instead of receiving an ``S`` that an old round would absorb.
    """

    READY, RUNNING, SETTLING, DRAINING = "ready", "running", "settling", "draining"

    def __init__(self, transport, round_timeout_s: float = 4.0, drain_quiet_s: float | None = None,
                 port_wait_s: float = 0.2):
        self.transport = transport
        self.round_timeout_s = round_timeout_s
        self.drain_quiet_s = 3.0 * round_timeout_s if drain_quiet_s is None else drain_quiet_s
        self.port_wait_s = port_wait_s
        self.decoder = TiersDecoder()
        self.state = self.READY
        self.rounds_started = 0  # requests made
        self.starts_sent = 0
        self.stale_matrices = 0  # matrices of timed-out or abandoned requests, discarded
        self._deadline: float | None = None
        self._pending = False  # a request whose S waits for the firmware to be ready
        self._reconnections_at_start = 0  # the port's reconnections when the last S went out
        self._last_rx = time.monotonic()
        self._printed: RangeMatrixMessage | None = None  # the last matrix the firmware printed

    @property
    def running(self) -> bool:
        """A request is open (its S sent or held back)."""
        return self._deadline is not None

    def start_round(self) -> int:
        """Request a round; returns its number. The ``S`` goes out now if the firmware is ready,
        else as soon as it is (exactly ``S``: any other byte would pause a running round).

        Raises :class:`PortError` if the port is away (after ``port_wait_s``)."""
        if self.running:
            raise HardwareError(f"port {self.transport.url!r}: round {self.rounds_started} still running")
        self._handle(self._pump())  # output already received (a banner, the end of a stale round)
        self.rounds_started += 1
        self._deadline = time.monotonic() + self.round_timeout_s
        self._pending = True
        try:
            self._send_if_ready()
        except PortError:
            self._deadline, self._pending = None, False
            raise
        return self.rounds_started

    def abandon(self) -> None:
        """Give up the open request (e.g. the env resets): its matrix, if it comes, is stale."""
        if self.running:
            self._deadline, self._pending = None, False
            if self.state == self.RUNNING:  # its S went out: the firmware runs it to its end
                self.state = self.DRAINING

    def poll(self) -> RangeMatrixMessage | None:
        """The open request's matrix once it has arrived; None while it runs.

        Raises :class:`RoundFailed` when the request times out (a missing anchor hangs the
        firmware silently), its matrix arrived damaged, or the firmware ended the round (or
        rebooted) without a matrix the driver could read.
        """
        matrix = self._handle(self._pump())
        if matrix is not None:
            return matrix
        if self.state == self.DRAINING and time.monotonic() - self._last_rx > self.drain_quiet_s:
            self.state = self.READY  # silent for long: no round is printing any more
        if self._pending:
            try:
                self._send_if_ready()
            except PortError as err:
                self._deadline, self._pending = None, False
                raise RoundFailed(self.transport.url, self.rounds_started, str(err)) from err
        if self.running and time.monotonic() > self._deadline:
            sent = not self._pending
            self._deadline, self._pending = None, False
            if sent:
                self.state = self.DRAINING  # the firmware may still finish it: its matrix is stale
            raise RoundFailed(self.transport.url, self.rounds_started,
                              f"no matrix within {self.round_timeout_s:.1f} s" + (
                                  " (an anchor missing or hung?)" if sent else
                                  " (the firmware never became ready for a start: a previous round still running?)"))
        return None

    def _handle(self, messages: list) -> RangeMatrixMessage | None:
        """Advance the state machine over decoded messages; the open request's matrix if any."""
        matrix, failure = None, None
        for message in messages:  # all of them, even after a failure: the state must follow
            if isinstance(message, RangeMatrixMessage):
                message = self._with_repeats(message)
            elif isinstance(message, RejectedMatrix):
                self._printed = None  # what the firmware holds now is unknown
            if isinstance(message, (RangeMatrixMessage, RejectedMatrix)):
                if self.state == self.RUNNING:
                    self.state = self.SETTLING
                    self._deadline = None
                    if isinstance(message, RejectedMatrix):
                        failure = message.reason
                    else:
                        matrix = message
                elif isinstance(message, RangeMatrixMessage):
                    self.stale_matrices += 1
            elif isinstance(message, WaitingForStart):
                if self.state == self.RUNNING:  # the round ended without a matrix
                    self._deadline = None
                    failure = "the firmware ended the round without a readable matrix"
                self.state = self.READY
            elif isinstance(message, Banner):
                self._printed = None  # a boot clears the matrix's RAM
                if self.state == self.RUNNING:
                    # A boot banner read after our S: the board rebooted after it (the round is
                    # gone) or before it, the banner still in flight when the S went out (then
                    # the S started a round whose matrix will come). The bytes cannot tell the
                    # two apart; the port can: a power cycle (USB unplug) since the S means the S
                    # died with the board. Otherwise fail the request and drain, so that a matrix
                    # is never credited to the next request (its S would be absorbed by this round).
                    self._deadline = None
                    failure = "the firmware printed its boot banner after the start (rebooted)"
                    power_cycled = getattr(self.transport, "reconnections", 0) > self._reconnections_at_start
                    self.state = self.READY if power_cycled else self.DRAINING
                else:
                    self.state = self.READY
        if failure is not None:
            raise RoundFailed(self.transport.url, self.rounds_started, failure)
        return matrix

    def _with_repeats(self, message: RangeMatrixMessage) -> RangeMatrixMessage:
        """The message with ``repeated`` set against the matrix printed before it (any, stale
        ones included: the firmware's cells live across rounds), which it then replaces."""
        before, self._printed = self._printed, message
        return replace(message, repeated=repeated_cells(before, message))

    def run_round(self) -> RangeMatrixMessage:
        self.start_round()
        while True:
            message = self.poll()
            if message is not None:
                return message
            time.sleep(0.005)

    def _pump(self) -> list:
        data = self.transport.read_available()
        if data:
            self._last_rx = time.monotonic()
        try:
            return self.decoder.feed(data)
        except Exception:  # noqa: BLE001 (decoders never raise; a bug there must not end the round)
            self.decoder = TiersDecoder()
            return []

    def _send_if_ready(self) -> None:
        if self._pending and self.state == self.READY:
            self.transport.write(START, wait_s=self.port_wait_s)
            self._reconnections_at_start = getattr(self.transport, "reconnections", 0)
            self._pending = False
            self.starts_sent += 1
            self.state = self.RUNNING


class PansShellTagDriver:
    """A PANS tag in shell mode streaming ``lec`` reports.

    Stock PANS *toggles* ``lec`` (sent to a streaming tag it stops the stream), repeats the
    previous command on an empty line (so the two ``\\r`` that enter the shell can toggle it
    too), and returns to generic (TLV) mode after any reboot. So the driver never sends ``lec``
    blindly: :meth:`ensure_streaming` first listens for reports and only when none come enters
    the shell and starts the stream, then checks that reports arrive. A watchdog in
    :meth:`poll` does the same when the stream has been silent for ``watchdog_s`` or the port
    reconnected (a power cycle or USB re-enumeration reboots the tag into generic mode).
    """

    def __init__(self, transport, pace_s: float = 0.0, retries: int = 3, prompt_timeout_s: float = 1.0,
                 listen_s: float = 0.3, watchdog_s: float = 1.0):
        self.transport = transport
        self.pace_s, self.retries, self.prompt_timeout_s = pace_s, retries, prompt_timeout_s
        self.listen_s, self.watchdog_s = listen_s, watchdog_s
        self.decoder = ShellDecoder()
        self.latest: LocationReport | None = None
        self.latest_time: float = -np.inf
        self.reports = 0
        self.restarts = 0  # watchdog restarts of the stream (reboots, lost streams)
        self._last_attempt = -np.inf
        self._reconnections = getattr(transport, "reconnections", 0)
        self._generic_seen = False

    def enter_shell(self, retries: int | None = None) -> None:
        """Two ``\\r`` (spaced), wait for ``dwm> ``; retry when the device answers in generic mode."""
        retries = self.retries if retries is None else retries
        for _ in range(retries):
            self.transport.write(b"\r", wait_s=0.2)
            time.sleep(0.05)
            self.transport.write(b"\r", wait_s=0.2)
            try:
                self.transport.read_until(PROMPT, self.prompt_timeout_s)
                return
            except DeviceTimeout:
                continue
        what = "PANS shell prompt after 2x Enter (the TIERS anchor firmware has no shell: anchor/tag ports swapped?)"
        raise DeviceTimeout(self.transport.url, what, self.prompt_timeout_s * retries)

    def command(self, text: str) -> None:
        self.transport.write(text.encode() + b"\r", pace_s=self.pace_s, wait_s=0.2)

    def ensure_streaming(self, attempts: int = 2) -> None:
        """Make the ``lec`` stream run without ever toggling a running one off.

        Raises :class:`DeviceTimeout` when no report arrives after ``attempts`` restarts and
        :class:`PortError` while the port is away."""
        if self._listen(self.listen_s):
            return
        for _ in range(attempts):
            self.transport.flush_input()
            self.decoder = ShellDecoder()
            self.enter_shell()
            if self._listen(self.listen_s):  # the empty lines repeated a stopped 'lec'
                return
            self.command("lec")
            if self._listen(max(self.listen_s, 0.5)):
                return
        raise DeviceTimeout(self.transport.url, "lec reports after starting the stream", self.listen_s)

    start_lec = ensure_streaming

    def poll(self) -> list[LocationReport]:
        """Reports that arrived since the last call (the newest is also kept in ``latest``);
        restarts the stream when the watchdog says so (errors are kept for the next try)."""
        out = self._read()
        now = time.monotonic()
        reconnections = getattr(self.transport, "reconnections", 0)
        reconnected = reconnections != self._reconnections
        silent = now - self.latest_time > self.watchdog_s
        if (reconnected or silent or self._generic_seen) and now - self._last_attempt > self.watchdog_s:
            self._last_attempt = now
            if getattr(self.transport, "connected", None) is None or self.transport.connected.is_set():
                self._reconnections, self._generic_seen = reconnections, False
                try:
                    self.ensure_streaming(attempts=1)
                    self.restarts += 1
                except HardwareError:
                    pass  # still away or rebooting: the next watchdog period tries again
        return out

    def _read(self) -> list[LocationReport]:
        out = []
        try:
            messages = self.decoder.feed(self.transport.read_available())
        except Exception:  # noqa: BLE001 (decoders never raise; a bug there must not stop the tag)
            self.decoder, messages = ShellDecoder(), []
        for message in messages:
            if isinstance(message, LocationReport):
                out.append(message)
            elif isinstance(message, GenericModeError):
                self._generic_seen = True  # the device reset into generic mode
        if out:
            self.latest, self.latest_time = out[-1], time.monotonic()
            self.reports += len(out)
        return out

    def _listen(self, seconds: float) -> bool:
        """Read for up to ``seconds``; True as soon as a report arrived."""
        return _listen(self._read, seconds)


class TiersTagDriver:
    """A tag running the TIERS localization build (``Localization/Initiator``).

    Its ``main`` loop reads at most one UART byte per iteration into a latched flag and polls
    the next anchor only while that flag is ``S``; ``F`` prints ``END`` and leaves the loop for
    good (until a reset), any other byte pauses it. After power-up it prints its banner and
    waits. So the driver sends ``S`` (idempotent: the flag is latched) when no line arrives,
    never ``F``, and again after a reboot (the banner, a port reconnection or a silence longer
    than ``watchdog_s``: an anchor that does not answer costs 25 polls of 66.7 ms per line).

    The same surface as :class:`PansShellTagDriver` for :class:`~uwb_env.hardware.backend.HardwareWorld`:
    ``poll()`` returns the reports that arrived, ``latest`` / ``latest_time`` hold the newest.
    Anchors are named ``"1"`` .. ``"4"`` (the TIERS anchor IDs; anchor index = ID - 1). Ranges
    of anchors that did not answer (255 bytes) are absent; ranges whose std exceeds
    ``max_std_m`` (a partial sum leaked from a timed-out anchor, see
    :mod:`~uwb_env.hardware.tiers_tag`) or that jump more than ``max_jump_m`` from the anchor's
    recent readings (a character lost inside a byte) are dropped and counted in
    ``ranges_rejected``; damaged lines are counted in ``lines_rejected``.
    """

    ANCHOR_IDS = ("1", "2", "3", "4")

    def __init__(self, transport, max_std_m: float = 0.3, max_jump_m: float = 0.5, listen_s: float = 0.3,
                 line_timeout_s: float = 2.5, watchdog_s: float = 2.5):
        if not max_std_m > 0:
            raise ValueError(f"max_std_m={max_std_m!r}: must be > 0")
        self.transport, self.max_std_m, self.max_jump_m = transport, max_std_m, max_jump_m
        self._history: dict[int, deque] = {}
        self.listen_s, self.line_timeout_s, self.watchdog_s = listen_s, line_timeout_s, watchdog_s
        self.decoder = TiersTagDecoder()
        self.latest: LocationReport | None = None
        self.latest_time: float = -np.inf
        self.reports = 0
        self.lines_rejected = 0
        self.ranges_rejected = 0
        self.restarts = 0  # start bytes sent by the watchdog (reboots, silence)
        self._last_attempt = -np.inf
        self._reconnections = getattr(transport, "reconnections", 0)
        self._booted = False

    def ensure_streaming(self, attempts: int = 1) -> None:
        """Listen ``listen_s`` for a line; if none comes, send ``S`` and wait up to
        ``line_timeout_s`` (a line takes ~0.1 s, 1.7 s more per anchor that does not answer),
        ``attempts`` times. :class:`DeviceTimeout` when no line arrives."""
        if self._listen(self.listen_s):
            return
        for _ in range(attempts):
            self.transport.write(START)  # latched: harmless if the tag is already polling
            if self._listen(self.line_timeout_s):
                return
        raise DeviceTimeout(self.transport.url, "TIERS tag lines after the start byte", self.line_timeout_s)

    def _listen(self, seconds: float) -> bool:
        return _listen(self._read, seconds)

    start_lec = ensure_streaming

    def poll(self) -> list[LocationReport]:
        out = self._read()
        now = time.monotonic()
        reconnections = getattr(self.transport, "reconnections", 0)
        reconnected = reconnections != self._reconnections
        silent = now - self.latest_time > self.watchdog_s
        if self._booted or ((reconnected or silent) and now - self._last_attempt > self.watchdog_s):
            if getattr(self.transport, "connected", None) is None or self.transport.connected.is_set():
                self._last_attempt, self._reconnections, self._booted = now, reconnections, False
                try:
                    self.transport.write(START)  # latched: harmless if the tag is already polling
                    self.restarts += 1
                except HardwareError:
                    pass  # still away: the next watchdog period tries again
        return out

    def _read(self) -> list[LocationReport]:
        try:
            messages = self.decoder.feed(self.transport.read_available())
        except Exception:  # noqa: BLE001 (decoders never raise; a bug there must not stop the tag)
            self.decoder, messages = TiersTagDecoder(), []
        out = []
        for message in messages:
            if isinstance(message, TiersTagLine):
                out.append(self._report(message))
            elif isinstance(message, RejectedTagLine):
                self.lines_rejected += 1
            elif isinstance(message, OtherTagLine) and message.text.startswith(BANNER_INIT):
                self._booted = True  # rebooted: waits for S
        if out:
            self.latest, self.latest_time = out[-1], time.monotonic()
            self.reports += len(out)
        return out

    def _report(self, line: TiersTagLine) -> LocationReport:
        keep = line.plausible(self.max_std_m) & self._continuous(line)
        self.ranges_rejected += int((line.answered & ~keep).sum())
        ranges = tuple(AnchorRange(str(a), (0.0, 0.0, 0.0), float(d))
                       for a, d, k in zip(line.anchor_ids, line.mean_m, keep, strict=True) if k)
        return LocationReport(ranges, None, None, "tiers")

    def _continuous(self, line: TiersTagLine) -> np.ndarray:
        """A range within ``max_jump_m`` of the median of the anchor's last three readings
        (those less than a second old; fewer than two: accepted). A character lost on the wire
        inside a byte still parses (``150`` -> ``15``: 1.50 m -> 0.15 m); a tag cannot move that
        far between two lines ~0.1 s apart."""
        now = time.monotonic()
        ok = np.ones(len(line.mean_m), dtype=bool)
        for j, r in enumerate(line.mean_m):
            if not np.isfinite(r):
                continue
            recent = [v for t, v in self._history.get(j, ()) if now - t < 1.0]
            if len(recent) >= 2 and abs(r - float(np.median(recent))) > self.max_jump_m:
                ok[j] = False
            self._history.setdefault(j, deque(maxlen=3)).append((now, float(r)))
        return ok


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


def _listen(read, seconds: float) -> bool:
    """Call ``read`` for up to ``seconds``; True as soon as it returns something."""
    deadline = time.monotonic() + seconds
    while True:
        if read():
            return True
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.01)
