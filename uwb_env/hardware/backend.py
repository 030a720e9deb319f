"""The hardware ranging backend: the simulator's World interface on real (or emulated) devices.

:class:`HardwareWorld` is what :class:`~uwb_env.system.LocalizationSystem` steps instead of
the simulated world: calibration rounds send the TIERS start byte and wait for the real
matrix; tag ranges come from the tags (stock-PANS ``lec`` streams, or the lines of tags
running the TIERS localization build); anchor motion comes from a
user-supplied odometry source (a callable returning each anchor's displacement since the
last call, in the robots' odometry frame: held back until that frame's transform to the
calibration's is fitted from the motion, ``odometry_frame.py``) or the anchors are static.
There is no ground truth: ``anchors_true`` and ``tags_true`` are NaN, so truth-based metrics
are NaN and the env uses its residual proxy.
It runs in wall-clock time (each step waits for the next ``dt_s`` tick) and is not
deterministic.

Range bias: the range model's slope/offset correction applies per firmware, configurable in
:class:`HardwareConfig` (the TIERS SS-TWR firmware has the measured +0.36 m bias; stock PANS
is usually antenna-delay calibrated).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from uwb_env.config import ConfigBase, SimConfig
from uwb_env.hardware.drivers import PansShellTagDriver, TiersAnchorDriver, TiersTagDriver
from uwb_env.hardware.errors import HardwareError
from uwb_env.hardware.odometry_frame import ODOMETRY_FRAMES, HeldBackOdometry, OdometryFrameTracker
from uwb_env.hardware.pans_anchor import PansAnchorDriver, RoleSwitchCalibrator
from uwb_env.hardware.tiers import firmware_pair_order, unwrap_negative_means
from uwb_env.localization.errors import LocalizationError
from uwb_env.measurements import RangeMatrix
from uwb_env.sim.calibration_round import RoundTiming
from uwb_env.sim.ranging import RangeModel
from uwb_env.sim.world import RoundRunner


@dataclass(frozen=True)
class HardwareConfig(ConfigBase):
    tiers_correct_bias: bool = True
    pans_correct_bias: bool = False
    round_timeout_s: float = 4.0
    # all-PANS: one anchor's role switch (two reboots, shell entries, configuration) plus
    # K ranges at 10 Hz; an estimate for the busy-channel model, not a measurement
    pans_role_switch_s: float = 3.0
    tag_range_max_age_s: float = 0.5  # older lec reports count as missing
    # a lec range farther than this from the distance between the tag's own position estimate
    # (same line) and the anchor's reported position was damaged on the wire: rejected, counted
    tag_range_consistency_m: float = 0.5
    tag_watchdog_s: float = 1.0  # a tag silent this long (or reconnected) gets its stream restarted
    realtime: bool = True  # wait for each dt_s tick (False: step as fast as called, e.g. replay)
    # the frame odometry_source reports in: "estimate" (the robots' own odometry frame; its
    # transform to the calibration's frame is fitted from motion, displacements are held back
    # until then: hardware/odometry_frame.py) or "calibration" (already in the estimate frame)
    odometry_frame: str = "estimate"
    odometry_frame_margin_chi2: float = 16.0  # every rival transform this much worse
    odometry_frame_max_std_deg: float = 5.0  # the fitted angle's largest std

    def __post_init__(self) -> None:
        self._positive("round_timeout_s", "pans_role_switch_s", "tag_range_max_age_s", "tag_range_consistency_m",
                       "tag_watchdog_s", "odometry_frame_margin_chi2", "odometry_frame_max_std_deg")
        self._choice("odometry_frame", ODOMETRY_FRAMES)


class CalibrationFailed(LocalizationError):
    """A hardware round produced no usable matrix (the env reports it and keeps odometry)."""


class HardwareRound:
    """A round running on the devices; the same surface as the simulator's round."""

    def __init__(self, start_time_s: float, expected_s: float, n: int, initiators: tuple[int, ...] | None = None,
                 pairs: list[tuple[int, int]] | None = None, measurements_per_pair: int | None = None):
        self.start_time_s = start_time_s
        self.measurements_per_pair = measurements_per_pair  # K the round was started with (None: the config's)
        self.end_time_s = start_time_s + expected_s
        self.expected_s = expected_s
        self.initiators = initiators  # None: a team round; (i,): anchor i re-located against the others
        if pairs is None:  # each initiator in turn, its responders in index order
            idx = np.arange(n) if initiators is None else np.asarray(initiators)
            pairs = [(int(i), j) for i in idx for j in range(n) if j != i]
        # the ordered pairs in the order the devices range them (the links the renderer draws)
        self.initiator = np.array([i for i, _ in pairs])
        self.responder = np.array([j for _, j in pairs])
        self.done = False
        # each ordered pair's time (absolute, aligned with ``initiator``), where the firmware's
        # schedule is known (TIERS: set when the matrix arrives); None: no carry to the midpoint
        self.times_s: np.ndarray | None = None
        self.matrix: RangeMatrix | None = None
        self.error: str | None = None
        self.elapsed_s = 0.0

    @property
    def progress(self) -> float:
        return 1.0 if self.done else min(self.elapsed_s / self.expected_s, 0.99)

    def result(self) -> RangeMatrix:
        if self.matrix is None:
            raise CalibrationFailed(self.error or "round failed")
        return self.matrix


class HardwareWorld(RoundRunner):
    """See the module docstring. ``tags``: one driver per tag, all of one firmware: PANS shell
    drivers (``anchor_ids``: the ID4 labels the tags report for anchors 0..N-1, in order) or
    TIERS tag drivers (anchor IDs 1..4 are anchors 0..3; ``anchor_ids`` is not needed)."""

    has_ground_truth = False

    def __init__(self, config: SimConfig, anchor: TiersAnchorDriver | RoleSwitchCalibrator,
                 tags: list[PansShellTagDriver | TiersTagDriver],
                 hardware: HardwareConfig | None = None, anchor_ids: list[str] | None = None,
                 odometry_source: Callable[[float], np.ndarray] | None = None,
                 move_callback: Callable[[np.ndarray, np.ndarray, np.ndarray], None] | None = None,
                 range_model: RangeModel | None = None):
        self.role_switching = isinstance(anchor, RoleSwitchCalibrator)
        if not self.role_switching and config.n_anchors != 4:
            raise ValueError(f"n_anchors={config.n_anchors!r}: the TIERS firmware calibrates exactly 4 anchors")
        if self.role_switching and len(anchor.anchors) != config.n_anchors:
            raise ValueError(f"anchors: {len(anchor.anchors)} PANS anchor ports for n_anchors={config.n_anchors}")
        if len(tags) != config.n_tags:
            raise ValueError(f"tags: {len(tags)} tag ports for n_tags={config.n_tags}: give one port per tag "
                             f"or set sim.n_tags={len(tags)}")
        self.config = config
        self.hardware = hardware or HardwareConfig()
        self.anchor, self.tags = anchor, tags
        tiers_tags = [isinstance(t, TiersTagDriver) for t in tags]
        if any(tiers_tags) and not all(tiers_tags):
            raise RadioCompatibilityError("tags: TIERS-build and PANS tags in one deployment range to different "
                                          "anchor sets; use one tag firmware")
        self.tag_firmware = "tiers" if tags and all(tiers_tags) else "pans"
        if self.tag_firmware == "tiers" and anchor_ids is None:
            anchor_ids = list(TiersTagDriver.ANCHOR_IDS)
        if anchor_ids is None:
            raise ValueError("anchor_ids: the IDs (4 hex digits, e.g. '1151') the tags report for anchors "
                             f"0..{config.n_anchors - 1}, in anchor order; `uwb-env emulate` prints the emulator's")
        anchor_ids = [str(a).upper() for a in anchor_ids]
        if len(anchor_ids) != config.n_anchors or len(set(anchor_ids)) != len(anchor_ids):
            raise ValueError(f"anchor_ids={anchor_ids!r}: expected {config.n_anchors} distinct IDs")
        self.anchor_ids = anchor_ids
        for tag in tags:
            tag.watchdog_s = self.hardware.tag_watchdog_s
        self._inconsistent_ranges = 0  # lec ranges inconsistent with their own line (damaged)
        self.means_unwrapped = 0  # TIERS matrix cells whose negative mean had wrapped (uint8)
        self.means_wrap_ambiguous = 0  # pairs where both directions may have wrapped
        self.stale_cells_dropped = 0  # TIERS matrix cells repeating the previous matrix (a missed F)
        self.unknown_anchor_ids: set[str] = set()  # IDs the tags reported that are not in anchor_ids
        self.range_model = range_model or RangeModel(config.ranging)
        # What the estimator undoes, per firmware (stock PANS is usually antenna-delay calibrated;
        # TIERS tags run the same SS-TWR code as the calibration build, with its bias).
        tag_bias = self.hardware.tiers_correct_bias if self.tag_firmware == "tiers" else self.hardware.pans_correct_bias
        self.tag_correction = self._correction(tag_bias)
        # calibration ranges: TIERS SS-TWR (biased) or PANS anchors surveyed as tags
        self.round_correction = self._correction(self.hardware.pans_correct_bias if self.role_switching
                                                 else self.hardware.tiers_correct_bias)
        self.timing = RoundTiming.fit(config.calibration)
        self.odometry = HeldBackOdometry(config.odometry)  # its variance model predicts the drift
        self.odometry_source = odometry_source
        self.odometry_frame = OdometryFrameTracker(config, self.hardware.odometry_frame if odometry_source else
                                                   "calibration", self.hardware.odometry_frame_margin_chi2,
                                                   self.hardware.odometry_frame_max_std_deg)
        self.motion = _MotionCommands(move_callback)
        self.dt_s = config.dt_s
        self.round: HardwareRound | None = None
        self.frame_rotation, self.frame_origin = np.eye(config.dim), np.zeros(config.dim)
        nan = np.full((config.n_anchors, config.dim), np.nan)
        self.anchors_true, self.tags_true = nan, np.full((config.n_tags, config.dim), np.nan)

    # -- lifecycle -----------------------------------------------------------------------------
    def reset(self, rng: np.random.Generator) -> None:
        self.rng = rng
        self.time_s, self.step_count = 0.0, 0
        self.anchors_est = np.zeros((self.config.n_anchors, self.config.dim))
        self.odometry.reset(self.config.n_anchors, rng, self.config.dim)
        self.odometry_frame.reset(self.odometry)
        if self.round is not None and not self.round.done:
            self.anchor.abandon()  # its matrix, if the firmware still prints it, is stale
        self.round = None
        for tag in self.tags:
            try:
                tag.ensure_streaming()  # never toggles a running stream off
            except HardwareError:
                pass  # a tag away or rebooting: its watchdog keeps trying, its ranges are NaN meanwhile
        if self.odometry_source is not None:
            # the motion while the episode was set up: before any estimate, nothing to move
            self.odometry_source(0.0)
        self._t0 = time.monotonic()

    def step(self) -> None:
        if self.hardware.realtime:
            wait = self._t0 + (self.step_count + 1) * self.dt_s - time.monotonic()
            if wait > 0:
                time.sleep(wait)
        self.step_count += 1
        self.time_s = self.step_count * self.dt_s
        if self.odometry_source is not None:
            moved = np.asarray(self.odometry_source(self.dt_s), dtype=float)
            if moved.shape != self.anchors_est.shape or not np.isfinite(moved).all():
                raise ValueError(f"odometry_source returned {moved!r}: expected finite displacements of shape "
                                 f"{self.anchors_est.shape} (one row per anchor, metres since the last call)")
            self.anchors_est += self.odometry_frame.step(self.time_s, moved)
            self.odometry.note_motion(moved)
        for tag in self.tags:
            tag.poll()
        if self.round is not None and not self.round.done:
            self._poll_round()

    def _poll_round(self) -> None:
        rnd = self.round
        rnd.elapsed_s = self.time_s - rnd.start_time_s
        # A round still running holds the channel past the timing model's estimate (the
        # firmware retries an unanswered poll after its 67 ms RX timeout): busy until done.
        rnd.end_time_s = max(rnd.end_time_s, self.time_s)
        try:
            message = self.anchor.poll()
        except HardwareError as err:  # RoundFailed, or the port went away: a failed round, never stuck
            rnd.done, rnd.error = True, str(err)
            return
        if message is not None and self.role_switching:
            rnd.done, rnd.matrix = True, message
        elif message is not None:
            rnd.done = True
            mean, unwrapped, ambiguous = unwrap_negative_means(message.mean_m)
            self.means_unwrapped += unwrapped
            self.means_wrap_ambiguous += ambiguous
            valid = mean != 0  # 0: a cell the firmware never filled (a negative mean is a real reading)
            if message.repeated is not None:
                # A cell repeating the previous matrix byte for byte is most likely one whose F
                # broadcast ID 1 missed: an earlier round's range, wrong by however far the pair
                # moved since. Dropped (the reverse direction usually has the pair); on a still
                # team a fresh cell repeats by chance (~2 % of cells) and costs only that cell.
                self.stale_cells_dropped += int(np.count_nonzero(message.repeated & valid))
                valid &= ~message.repeated
            np.fill_diagonal(valid, False)
            k = rnd.measurements_per_pair or self.config.calibration.measurements_per_pair
            rnd.matrix = RangeMatrix(np.where(valid, mean, np.nan), np.where(valid, message.std_m, np.nan),
                                     np.where(valid, k, 0))
            # The firmware ranges its pairs one after another (tiers.firmware_pair_order), each its K
            # polls and then its F broadcast's timeout: the simulator's schedule (RoundTiming), whose
            # pair order is the firmware's. Each pair at its polls' mean time in that schedule,
            # stretched to the round's measured duration (retries lengthen it, and the matrix's
            # arrival time includes them), so the system carries the ranges to the round's midpoint
            # as in simulation.
            rnd.times_s = rnd.start_time_s + self._pair_offsets_s(rnd, k) * (self.time_s - rnd.start_time_s)

    def _pair_offsets_s(self, rnd: HardwareRound, k: int) -> np.ndarray:
        """Each ordered pair's mean exchange time in a team round of the timing model with K = ``k``,
        as a fraction of the round (aligned with ``rnd.initiator`` / ``rnd.responder``)."""
        n = self.config.n_anchors
        offsets, initiator, responder = self.timing.schedule(n, k)
        if not (np.array_equal(initiator[::k], rnd.initiator) and np.array_equal(responder[::k], rnd.responder)):
            raise RuntimeError("a TIERS round whose pair order is not the timing model's (both are the firmware's)")
        return offsets.reshape(-1, k).mean(1) / self.timing.duration_s(n, k)

    def _correction(self, correct_bias: bool) -> RangeModel:
        if correct_bias == self.range_model.config.correct_bias:
            return self.range_model
        return RangeModel(self.config.ranging.replace(correct_bias=correct_bias))

    # -- the World interface -------------------------------------------------------------------
    def calibration_applied(self, positions: np.ndarray, var_m2: np.ndarray, start_s: float, end_s: float) -> None:
        """A team calibration was applied (``positions`` at its round's midpoint): fit the odometry
        frame's transform while it is unknown (``odometry_frame.fit``, ``.rotation``; without an
        odometry source the tracker is in ``"calibration"`` mode and does nothing)."""
        self.anchors_est += self.odometry_frame.calibration_applied(positions, var_m2, start_s, end_s)

    def anchor_calibration_applied(self, anchor: int, start_s: float, end_s: float) -> None:
        """A per-anchor round re-located ``anchor``: while displacements are held back, its
        estimate is the solution at the round's midpoint, so the motion since then is what it
        lacks (``restart_drift`` has just cleared it)."""
        self.odometry_frame.anchor_calibration_applied(anchor, start_s, end_s)

    def set_estimate_frame(self, rotation: np.ndarray, origin: np.ndarray) -> None:
        self.frame_rotation, self.frame_origin = rotation, origin

    def to_estimate_frame(self, points_world: np.ndarray) -> np.ndarray:
        return np.full_like(points_world, np.nan)  # no truth to express

    def measure_tag_ranges(self) -> np.ndarray:
        """(n_anchors, n_tags) latest ``lec`` ranges (NaN: missing or older than the age limit)."""
        out = np.full((self.config.n_anchors, self.config.n_tags), np.nan)
        now = time.monotonic()
        for t, tag in enumerate(self.tags):
            report = tag.latest
            if report is None or now - tag.latest_time > self.hardware.tag_range_max_age_s:
                continue
            for r in report.ranges:
                if r.anchor_id not in self.anchor_ids:
                    self.unknown_anchor_ids.add(r.anchor_id)
                elif self._consistent(r, report.position_m):
                    out[self.anchor_ids.index(r.anchor_id), t] = r.distance_m
                else:
                    self._inconsistent_ranges += 1
        return out

    @property
    def tag_ranges_rejected(self) -> int:
        """Tag ranges thrown away as damaged or implausible: ``lec`` ranges inconsistent with
        their own line, TIERS ranges with an implausible spread (see :class:`TiersTagDriver`)."""
        return self._inconsistent_ranges + sum(getattr(t, "ranges_rejected", 0) for t in self.tags)

    def _consistent(self, r, position_m) -> bool:
        """The range agrees with the tag's own position estimate in the same line (when the
        line has one and the anchors report configured positions): a dropped or inserted
        character that still parses as a number is caught here."""
        if position_m is None or not any(r.position_m):
            return True
        expected = float(np.linalg.norm(np.subtract(position_m, r.position_m)))
        return abs(r.distance_m - expected) <= self.hardware.tag_range_consistency_m

    def start_calibration_round(self, measurements_per_pair: int | None = None, initiators=None) -> HardwareRound:
        """A team round (``initiators`` None) or, on the all-PANS deployment, the anchors of
        ``initiators`` re-located one at a time (a per-anchor round: one index)."""
        n = self.config.n_anchors
        k = measurements_per_pair or self.config.calibration.measurements_per_pair
        if self.role_switching:
            order = tuple(range(n)) if initiators is None else tuple(int(i) for i in initiators)
            expected = len(order) * (self.hardware.pans_role_switch_s + 0.1 * k)
            self.round = HardwareRound(self.time_s, expected, n, None if initiators is None else order)
            try:
                self.anchor.start(order, k)
            except HardwareError as err:
                self.round.done, self.round.error = True, str(err)
            return self.round
        if initiators is not None:
            raise ValueError("initiators: the TIERS firmware ranges every pair in one round; per-anchor rounds need "
                             "the all-PANS deployment (connect_pans, role switching)")
        self.round = HardwareRound(self.time_s, self.timing.duration_s(n, k), n, pairs=firmware_pair_order(n),
                                   measurements_per_pair=k)
        try:
            self.anchor.start_round()
        except HardwareError as err:  # e.g. the anchor's port is away: a failed round, reported in infos
            self.round.done, self.round.error = True, str(err)
        return self.round

    def finish_calibration_round(self) -> HardwareRound:
        if self.round is None or not self.round.done:
            raise RuntimeError("no finished calibration round to collect")
        finished, self.round = self.round, None
        return finished

    def close(self) -> None:
        if self.role_switching:
            self.anchor.close()
        else:
            self.anchor.transport.close()
        for transport in {t.transport for t in self.tags}:
            transport.close()


class _MotionCommands:
    """``calibrate_and_move`` on hardware: commands go to the user's robots via a callback."""

    def __init__(self, callback):
        self.callback = callback

    def command(self, rows: np.ndarray, headings: np.ndarray, speeds: np.ndarray) -> None:
        if self.callback is None:
            raise NotImplementedError("action_mode='calibrate_and_move' on hardware needs a move_callback "
                                      "that drives the robots")
        self.callback(rows, headings, speeds)


class RadioCompatibilityError(HardwareError, ValueError):
    """A deployment whose radios cannot talk to each other."""


def connect(config: SimConfig, anchor_url: str, tag_urls: list[str], *, pans_anchor_ids: list[str] | None = None,
            tag_firmware: str = "pans", hardware: HardwareConfig | None = None, recorder=None,
            odometry_source=None, move_callback=None, shell_pace_s: float = 0.0) -> HardwareWorld:
    """Open the ports (recording every byte when ``recorder`` is given) and build the backend.

    ``anchor_url``: TIERS autocalibration anchor ID 1 (calibration rounds); ``tag_urls``: one
    tag per simulated tag slot. ``tag_firmware="tiers"`` (all-TIERS): the tags run the TIERS
    localization build and range to boards running its ``Localization/Responders`` build with
    IDs 1..4 (anchors 0..3), one per robot beside the calibration anchor (the repository's
    calibration and localization builds are separate).
    ``tag_firmware="pans"`` (default): stock-PANS tags streaming ``lec``.

    Radio compatibility: the TIERS builds use their own frames and preamble code 10, stock PANS
    code 9 and its own TDMA MAC, so a PANS tag cannot range to anchors running TIERS firmware.
    Tags therefore range to a *second, PANS anchor set* carried by the same robots (one PANS
    anchor next to each TIERS anchor); ``pans_anchor_ids`` names them (the 16-bit IDs the tags
    report, e.g. ``"1151"``), in anchor order. Without it ``connect`` refuses
    (:class:`RadioCompatibilityError`) rather than return NaN ranges forever.
    """
    from uwb_env.hardware.transport import SerialTransport

    if tag_firmware not in ("pans", "tiers"):
        raise ValueError(f"tag_firmware={tag_firmware!r}: expected 'pans' or 'tiers'")
    if tag_firmware == "tiers" and pans_anchor_ids is not None:
        raise RadioCompatibilityError("pans_anchor_ids: TIERS tags range to the TIERS anchors (IDs 1..4), not to "
                                      "PANS anchors; leave pans_anchor_ids out")
    if tag_firmware == "pans" and tag_urls and pans_anchor_ids is None:
        raise RadioCompatibilityError(
            "pans_anchor_ids: stock-PANS tags cannot range to anchors running the TIERS firmware (different "
            "frames and preamble codes); give the IDs of the PANS anchors the tags range to (one per robot, "
            "in anchor order), e.g. pans_anchor_ids=['1150', '1151', '1152', '1153']")
    hardware = hardware or HardwareConfig()
    anchor = TiersAnchorDriver(SerialTransport(anchor_url, recorder=recorder), hardware.round_timeout_s)
    if tag_firmware == "tiers":
        tags = [TiersTagDriver(SerialTransport(url, recorder=recorder)) for url in tag_urls]
    else:
        tags = [PansShellTagDriver(SerialTransport(url, recorder=recorder), pace_s=shell_pace_s) for url in tag_urls]
    return HardwareWorld(config, anchor, tags, hardware, anchor_ids=pans_anchor_ids,
                         odometry_source=odometry_source, move_callback=move_callback)


def connect_pans(config: SimConfig, anchor_urls: list[str], tag_urls: list[str], *,
                 anchor_ids: list[str] | None = None, network_id: int = 0x1234, hardware: HardwareConfig | None = None,
                 recorder=None, odometry_source=None, move_callback=None, shell_pace_s: float = 0.0) -> HardwareWorld:
    """The all-PANS deployment: stock firmware everywhere (what every DWM1001 ships with).

    ``anchor_urls``: one port per anchor, in anchor order (each anchor is wired to the host, or
    to its robot's computer); ``tag_urls``: stock-PANS tags streaming ``lec``. The anchors' IDs
    are read from each anchor (``si``) unless ``anchor_ids`` gives them. Calibration re-locates
    anchors one at a time by role switching (:mod:`uwb_env.hardware.pans_anchor`): a per-anchor
    round (``action_mode="per_anchor"``) switches one anchor, a team round every anchor in turn.
    """
    from uwb_env.hardware.transport import SerialTransport

    if len(anchor_urls) != config.n_anchors:
        raise ValueError(f"anchor_urls: {len(anchor_urls)} ports for n_anchors={config.n_anchors}; give one port "
                         "per anchor or set sim.n_anchors")
    hardware = hardware or HardwareConfig()
    anchors = [PansAnchorDriver(SerialTransport(url, recorder=recorder), pace_s=shell_pace_s) for url in anchor_urls]
    if anchor_ids is None:
        anchor_ids = [a.read_id() for a in anchors]
    calibrator = RoleSwitchCalibrator(anchors, list(anchor_ids), network_id=network_id)
    tags = [PansShellTagDriver(SerialTransport(url, recorder=recorder), pace_s=shell_pace_s) for url in tag_urls]
    return HardwareWorld(config, calibrator, tags, hardware, anchor_ids=list(anchor_ids),
                         odometry_source=odometry_source, move_callback=move_callback)
