"""The all-TIERS deployment: tags running the TIERS localization build.

The codec is checked against the firmware's own arithmetic (``ss_init_main.c``: C truncation,
uint8 storage, 255 for an anchor that timed out, no comma after the last value), the emulator
against the firmware's control flow (banner, latched ``S``, ``F`` stops, the running sum that
leaks from a timed-out anchor), and an episode end to end over pseudo-terminals.
"""

import time

import numpy as np
import pytest
from uwb_env.agents.baselines import FixedIntervalPolicy

import uwb_env
from uwb_env.config import EnvConfig
from uwb_env.env.policy import rollout
from uwb_env.hardware.backend import RadioCompatibilityError, connect
from uwb_env.hardware.drivers import TiersTagDriver
from uwb_env.hardware.emulator import Emulator, Scene, TiersTagDevice, standard_setup
from uwb_env.hardware.errors import ParseError
from uwb_env.hardware.tiers_tag import (
    OtherTagLine,
    RejectedTagLine,
    TiersTagDecoder,
    TiersTagLine,
    encode_tag_line,
    parse_tag_line,
)
from uwb_env.hardware.transport import SerialTransport
from uwb_env.localization import rigid_align

STATIC = {"anchor_motion": {"model": "static"}, "tag_motion": {"model": "static"}}


def _firmware_line(means_m, stds_m, timed_out=()):
    """The printf loop of ss_init_main.c, written out independently of the codec."""
    values = []
    for j in range(4):
        if j + 1 in timed_out:
            cells = [255, 255, 255, 255]
        else:
            cells = []
            for v in (means_m[j], stds_m[j]):
                cm = int(v * 100)  # (int)(mean*100), truncation toward zero
                msb = int(v * 100 / 256)
                lsb = int(np.fmod(cm, 256))  # C's % keeps the dividend's sign
                cells += [msb % 256, lsb % 256]  # stored into uint8
        values += [0, j + 1, *cells, 0, 0, 0, 0]
    return ",".join(map(str, values)) + "\r\n"


def test_codec_matches_the_firmware_printf_and_reads_back():
    rng = np.random.default_rng(0)
    for _ in range(500):
        means = rng.uniform(0.05, 40.0, 4)
        stds = rng.uniform(0.0, 0.3, 4)
        silent = tuple(int(a) for a in np.flatnonzero(rng.random(4) < 0.2) + 1)
        expected = _firmware_line(means, stds, silent)
        m = np.where(np.isin(np.arange(1, 5), silent), np.nan, means)
        assert encode_tag_line(m, stds).decode() == expected
        line = parse_tag_line(expected)
        assert line.anchor_ids == (1, 2, 3, 4)
        answered = ~np.isin(np.arange(1, 5), silent)
        np.testing.assert_array_equal(line.answered, answered)
        np.testing.assert_allclose(line.mean_m[answered], np.floor(means[answered] * 100) / 100, atol=1e-9)


def test_a_negative_mean_wraps_like_the_firmware():
    # (int)(-5) % 256 = -5 -> uint8 251; msb (int)(-0.0195) = 0: read back as 2.51 m
    assert _firmware_line([-0.05, 1, 1, 1], [0.01] * 4).startswith("0,1,0,251,0,1,")
    assert parse_tag_line(_firmware_line([-0.05, 1, 1, 1], [0.01] * 4)).mean_m[0] == pytest.approx(2.51)


def test_damaged_lines_are_rejected_never_misread_and_the_decoder_never_raises():
    good = _firmware_line([1.5, 2.5, 3.5, 4.5], [0.02] * 4)
    with pytest.raises(ParseError):
        parse_tag_line(good.rstrip() + ",")  # the firmware prints no trailing comma
    values = good.strip().split(",")
    values[11] = "3"  # anchor 2's ID field
    with pytest.raises(ParseError):
        parse_tag_line(",".join(values))  # anchor IDs must be 1..4 in order
    rng = np.random.default_rng(1)
    misread = 0
    truth = parse_tag_line(good)
    for _ in range(2000):
        data = bytearray(good.encode())
        at = int(rng.integers(0, len(data) - 2))
        if rng.random() < 0.5:
            del data[at]  # a dropped character
        else:
            data.insert(at, int(rng.integers(0, 256)))  # an inserted byte
        out = TiersTagDecoder().feed(bytes(data))
        for m in out:
            assert isinstance(m, (TiersTagLine, RejectedTagLine, OtherTagLine))
            if isinstance(m, TiersTagLine) and m != truth:
                misread += 1
    # a dropped digit inside a byte still parses as a valid uint8 in some positions: those
    # misreads are what the driver's plausibility check and the tracker's residuals are for
    assert misread < 2000 * 0.35


def test_partial_sum_of_a_timed_out_anchor_is_caught_by_the_driver():
    scene = Scene(EnvConfig.from_dict({"sim": STATIC}).sim, seed=4, speedup=0.0)  # frozen: draws independent of wall time
    emu = Emulator(scene)
    url = emu.add("tag", TiersTagDevice(scene, 0, silent_after={2: 2}))  # anchor 2 answers twice, then stops
    with emu:
        driver = TiersTagDriver(SerialTransport(url))
        driver.ensure_streaming()
        deadline = time.monotonic() + 8.0
        while driver.reports < 3 and time.monotonic() < deadline:
            driver.poll()
            time.sleep(0.02)
        driver.transport.close()
    assert driver.reports >= 3
    ids = {r.anchor_id for r in driver.latest.ranges}
    assert ids == {"1", "4"}  # 2 timed out (255), 3 got 2's partial sum: dropped
    assert driver.ranges_rejected >= 3  # anchor 3, once per line
    truth = np.linalg.norm(scene.anchors_true()[0] - scene.tags_true()[0])
    got = next(r.distance_m for r in driver.latest.ranges if r.anchor_id == "1")
    assert abs(got - truth) < 0.8  # SS-TWR bias (+0.36 m) not yet corrected here


def test_the_emulated_tag_waits_for_s_and_stops_for_good_on_f():
    scene = Scene(EnvConfig.from_dict({"sim": STATIC}).sim, seed=5, speedup=0.0)  # frozen: draws independent of wall time
    dev = TiersTagDevice(scene, 0)
    t = 0.0
    assert b"Singled Sided Two Way Ranging INIT" in dev.poll(t)
    assert dev.poll(t + 1.0) == b""  # no line before S
    dev.receive(b"S", t + 1.0)
    out = dev.poll(t + 2.0)
    assert out.count(b"\r\n") >= 5  # ~12 lines per second with every anchor answering
    dev.receive(b"F", t + 2.0)
    assert dev.poll(t + 3.0).startswith(b"END\r\n")
    dev.receive(b"S", t + 3.0)
    assert dev.poll(t + 4.0) == b""  # F left the main loop: only a reset brings it back
    dev.reboot()
    dev.receive(b"S", t + 4.0)
    assert dev.poll(t + 5.0).count(b"\r\n") >= 5


def test_all_tiers_episode_end_to_end():
    cfg = EnvConfig.from_dict({"max_cycles": 30, "sim": STATIC})
    scene = Scene(cfg.sim, seed=3)
    emu, urls = standard_setup(scene, tag_firmware="tiers")
    with emu:
        world = connect(cfg.sim, urls["anchor"], [urls[f"tag_{i}"] for i in range(3)], tag_firmware="tiers")
        env = uwb_env.parallel_env(config=cfg, backend=world)
        result = rollout(env, FixedIntervalPolicy(12), seed=0)
        world.close()
    assert result.steps == 30
    assert env.system.calibration_count >= 3
    assert world.tag_firmware == "tiers"
    est, truth = env.system.world.anchors_est, scene.anchors_true()
    rot, trans = rigid_align(est, truth)
    tags = env.system.tag_fix @ rot.T + trans
    # TIERS tags carry the SS-TWR bias; the world undoes it like the calibration ranges'
    assert np.linalg.norm(tags - scene.tags_true(), axis=1).max() < 0.3


def test_connect_refuses_mixed_radios():
    sim = EnvConfig.from_dict({"sim": STATIC}).sim
    with pytest.raises(RadioCompatibilityError, match="pans_anchor_ids"):
        connect(sim, "loop://", ["loop://"] * 3, tag_firmware="tiers", pans_anchor_ids=["1150"] * 4)
    with pytest.raises(ValueError, match="tag_firmware"):
        connect(sim, "loop://", ["loop://"] * 3, tag_firmware="lora")


class _Chunks:
    """A transport that hands over recorded bytes one chunk per read."""

    url = "chunks://"

    def __init__(self, chunks):
        self.chunks = list(chunks)

    def read_available(self):
        return self.chunks.pop(0) if self.chunks else b""

    def write(self, data):
        pass


@pytest.mark.parametrize("max_jump_m", [np.inf, 0.5])
def test_lost_characters_inside_a_byte_are_rejected_by_continuity(max_jump_m):
    from uwb_env.hardware.emulator import Faults

    scene = Scene(EnvConfig.from_dict({"sim": STATIC}).sim, seed=6, speedup=0.0)  # frozen: draws independent of wall time
    dev = TiersTagDevice(scene, 0, faults=Faults(drop_char_probability=0.006), seed=7)
    dev.poll(0.0)
    dev.receive(b"S", 0.0)
    chunks = [dev.poll(0.1 * (i + 1)) for i in range(800)]  # ~80 s of lines, 0.1 s at a time
    driver = TiersTagDriver(_Chunks(chunks), max_jump_m=max_jump_m)
    accepted = []
    for _ in chunks:
        for report in driver.poll():
            accepted += [(int(r.anchor_id) - 1, r.distance_m) for r in report.ranges]
    truth = np.linalg.norm(scene.anchors_true()[:4] - scene.tags_true()[0], axis=1)
    err = np.array([d - truth[j] for j, d in accepted])
    wrong = np.abs(err - np.median(err)) > 0.5  # beyond noise around the SS-TWR bias
    assert driver.lines_rejected > 0 and len(accepted) > 1000
    if np.isfinite(max_jump_m):
        assert wrong.mean() < 0.002, wrong.mean()
        assert driver.ranges_rejected > 0
    else:
        assert wrong.mean() > 0.005, wrong.mean()  # without the check, lost characters pass as ranges


def test_a_wrapped_negative_calibration_mean_is_undone_where_the_reverse_direction_tells():
    from uwb_env.hardware.tiers import RangeMatrixMessage, TiersDecoder, encode_matrix, unwrap_negative_means

    true = np.array([[0, -0.05, 3.0, 4.0], [0.04, 0, 2.0, 5.0], [3.0, 2.0, 0, 2.3], [4.0, 5.0, 2.3, 0]])
    (message,) = [m for m in TiersDecoder().feed(encode_matrix(true, np.full((4, 4), 0.02)))
                  if isinstance(m, RangeMatrixMessage)]
    assert message.mean_m[0, 1] == pytest.approx(2.51)  # what the firmware's bytes say
    mean, unwrapped, ambiguous = unwrap_negative_means(message.mean_m)
    assert mean[0, 1] == pytest.approx(-0.05) and unwrapped == 1 and ambiguous == 0
    assert abs(mean[2, 3] - 2.30) <= 0.011 and abs(mean[1, 2] - 2.0) <= 0.011  # genuine ranges kept (C truncation)
    both = true.copy()
    both[1, 0] = -0.03  # both directions negative: both read ~2.5 m and agree; reported, not guessed
    both[0, 2:] = both[2:, 0] = both[1, 2:] = both[2:, 1] = [3.0, 4.0]  # co-located: same distances
    (message,) = [m for m in TiersDecoder().feed(encode_matrix(both, np.full((4, 4), 0.02)))
                  if isinstance(m, RangeMatrixMessage)]
    mean, unwrapped, ambiguous = unwrap_negative_means(message.mean_m)
    assert unwrapped == 0 and ambiguous == 1
