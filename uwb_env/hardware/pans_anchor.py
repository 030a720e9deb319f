"""Calibration with stock PANS firmware: anchors re-located one at a time by role switching.

Stock DWM1001 anchors do not range to each other on request. Host scripts survey them by
switching one anchor at a time to tag mode (``esauortiz/dwm1001_drivers:scripts/
autocalibration_sample_uart.py``): ``acts 0 1 0 0 0 1 1 2 0`` (tag; stationary detection on,
location engine off, LEDs and BLE on, UWB active), ``aurs 1 1`` (10 Hz), ``nis <network>``,
``reset``; after the reboot the shell is entered again and ``lec`` streams the ranges to the
anchors the tag picked (up to four); then ``acas <initiator> 0 0 1 1 2 0`` and ``nis`` set it
back to anchor and a second ``reset`` applies that. Every reboot returns to generic (TLV) mode,
so the shell is entered after each one.

:class:`RoleSwitchCalibrator` runs that procedure for the anchors of a round, in turn, on a
worker thread (each switch takes seconds; the env keeps stepping in wall-clock time), with an
explicit phase per anchor (``phase``) and a deadline for each. A round of one anchor is the
per-anchor calibration action (its ranges to the others, solved against their estimates); a
team round is every anchor in turn. Whatever happens, the anchor is set back to anchor mode
before the round ends (a failure, ``abandon()``), so no anchor is left as a tag.
"""

from __future__ import annotations

import re
import threading
import time
from dataclasses import dataclass

import numpy as np

from uwb_env.hardware.drivers import PansShellTagDriver, RoundFailed
from uwb_env.hardware.errors import DeviceTimeout, HardwareError
from uwb_env.hardware.pans_shell import PROMPT, LocationReport
from uwb_env.measurements import RangeMatrix

TAG_MODE = "acts 0 1 0 0 0 1 1 2 0"  # meas_mode, stnry_en, low_pwr, loc_en, enc, leds, ble, uwb, fw_upd
UPDATE_RATE = "aurs 1 1"  # 100 ms, moving and stationary: 10 Hz
_ADDR = re.compile(r"addr=x([0-9A-Fa-f]{4,16})")


def anchor_mode(initiator: bool) -> str:
    return f"acas {int(initiator)} 0 0 1 1 2 0"  # initiator, bridge, enc, leds, ble, uwb, fw_upd


class PansAnchorDriver:
    """One stock-PANS anchor's shell: its ID (``si``), role switches, and range collection."""

    def __init__(self, transport, pace_s: float = 0.0, prompt_timeout_s: float = 1.0, boot_timeout_s: float = 3.0):
        self.shell = PansShellTagDriver(transport, pace_s=pace_s, prompt_timeout_s=prompt_timeout_s)
        self.transport = transport
        self.boot_timeout_s = boot_timeout_s

    def _ask(self, command: str, timeout_s: float = 1.0) -> str:
        """Send one command and read its answer up to the prompt; if no prompt comes (the node
        rebooted into generic mode meanwhile), enter the shell and send it once more."""
        for attempt in range(2):
            self.transport.flush_input()
            self.shell.command(command)
            try:
                return self.transport.read_until(PROMPT, timeout_s).decode("ascii", errors="replace")
            except DeviceTimeout:
                if attempt:
                    raise
                self.shell.enter_shell()
        raise AssertionError("unreachable")

    def read_id(self) -> str:
        """The 16-bit ID tags report for this anchor (last 4 hex digits of ``si``'s address)."""
        self.shell.enter_shell()
        text = self._ask("si")
        m = _ADDR.search(text)
        if not m:
            raise HardwareError(f"port {self.transport.url!r}: no 'addr=x...' in the answer to 'si': {text[-120:]!r}")
        return m.group(1)[-4:].upper()

    def _reboot_into_shell(self) -> None:
        """``reset`` reboots into generic mode: knock (two Enters, a short wait for the prompt)
        until the shell answers or ``boot_timeout_s`` passes. Bytes sent while the node boots
        are lost, so each knock waits only briefly."""
        self.transport.write(b"reset\r", pace_s=self.shell.pace_s, wait_s=0.2)
        deadline = time.monotonic() + self.boot_timeout_s
        timeout, self.shell.prompt_timeout_s = self.shell.prompt_timeout_s, 0.25
        try:
            while True:
                try:
                    self.shell.enter_shell(retries=1)
                    return
                except DeviceTimeout:
                    if time.monotonic() > deadline:
                        raise
        finally:
            self.shell.prompt_timeout_s = timeout

    def to_tag(self, network_id: int) -> None:
        for command in (TAG_MODE, UPDATE_RATE, f"nis 0x{network_id:04X}"):
            self._ask(command)
        self._reboot_into_shell()

    def to_anchor(self, network_id: int, initiator: bool) -> None:
        for command in (anchor_mode(initiator), f"nis 0x{network_id:04X}"):
            self._ask(command)
        self._reboot_into_shell()

    def collect(self, ids: list[str], samples: int, timeout_s: float) -> dict[str, list[float]]:
        """Start ``lec`` and gather up to ``samples`` ranges to each anchor of ``ids``."""
        got: dict[str, list[float]] = {a: [] for a in ids}
        self.transport.flush_input()
        self.shell.command("lec")  # just rebooted: no stream runs, so this starts one
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and min(len(v) for v in got.values()) < samples:
            for report in self.shell._read():
                if isinstance(report, LocationReport):
                    for r in report.ranges:
                        if r.anchor_id in got and len(got[r.anchor_id]) < samples:
                            got[r.anchor_id].append(r.distance_m)
            time.sleep(0.02)
        return got


@dataclass
class _Round:
    initiators: tuple[int, ...]
    samples: int
    ranges: dict  # (i, j) -> list of ranges
    error: str | None = None
    done: bool = False


class RoleSwitchCalibrator:
    """Calibration rounds on stock-PANS anchors by role switching (see the module docstring).

    ``anchors``: one driver per anchor, in anchor order; ``anchor_ids``: their 16-bit IDs.
    ``start(initiators, samples)`` begins a round; ``poll()`` returns its
    :class:`~uwb_env.measurements.RangeMatrix` once done (rows of the initiators only), None
    while it runs, and raises :class:`RoundFailed` if it failed. ``phase`` says where it is.
    """

    def __init__(self, anchors: list[PansAnchorDriver], anchor_ids: list[str], network_id: int = 0x1234,
                 initiator_anchor: int = 0, collect_timeout_s: float = 3.0):
        if len(anchors) != len(anchor_ids):
            raise ValueError(f"anchor_ids: {len(anchor_ids)} IDs for {len(anchors)} anchors")
        self.anchors, self.anchor_ids = anchors, [a.upper() for a in anchor_ids]
        self.network_id, self.initiator_anchor = network_id, initiator_anchor
        self.collect_timeout_s = collect_timeout_s
        self.phase = "idle"
        self.rounds_started = 0
        self._round: _Round | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def start(self, initiators, samples: int) -> int:
        if self.running:
            raise HardwareError(f"calibration round {self.rounds_started} still running")
        self._round = _Round(tuple(int(i) for i in initiators), int(samples), {})
        self._stop.clear()
        self.rounds_started += 1
        self._thread = threading.Thread(target=self._run, args=(self._round,), daemon=True,
                                        name=f"role-switch round {self.rounds_started}")
        self._thread.start()
        return self.rounds_started

    def _run(self, rnd: _Round) -> None:
        try:
            for i in rnd.initiators:
                if self._stop.is_set():
                    raise HardwareError("round abandoned")
                self._survey(i, rnd)
        except HardwareError as err:
            rnd.error = f"{self.phase}: {err}"
        finally:
            self.phase = "idle"
            rnd.done = True

    def _survey(self, i: int, rnd: _Round) -> None:
        anchor = self.anchors[i]
        others = [self.anchor_ids[j] for j in range(len(self.anchors)) if j != i]
        self.phase = f"anchor {i}: to tag mode"
        anchor.to_tag(self.network_id)
        try:
            self.phase = f"anchor {i}: ranging"
            got = anchor.collect(others, rnd.samples, self.collect_timeout_s)
        finally:  # never leave an anchor in tag mode
            self.phase = f"anchor {i}: back to anchor mode"
            anchor.to_anchor(self.network_id, initiator=i == self.initiator_anchor)
        for j, a in enumerate(self.anchor_ids):
            if j != i:
                rnd.ranges[(i, j)] = got.get(a, [])

    def poll(self) -> RangeMatrix | None:
        rnd = self._round
        if rnd is None or not rnd.done:
            return None
        self._round = None
        if rnd.error is not None:
            raise RoundFailed("role switching", self.rounds_started, rnd.error)
        n = len(self.anchors)
        mean, std = np.full((n, n), np.nan), np.full((n, n), np.nan)
        count = np.zeros((n, n), dtype=int)
        for (i, j), values in rnd.ranges.items():
            if values:
                v = np.asarray(values)
                mean[i, j], count[i, j] = v.mean(), len(v)
                std[i, j] = v.std(ddof=1) if len(v) > 1 else 0.0
        if not count.any():
            raise RoundFailed("role switching", self.rounds_started, "no ranges between anchors arrived")
        return RangeMatrix(mean, std, count)

    def abandon(self) -> None:
        """Stop after the anchor being surveyed is back in anchor mode (waits for it)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=30.0)
        self._round = None

    def close(self) -> None:
        self.abandon()
        for anchor in self.anchors:
            anchor.transport.close()
