"""The emulated TIERS anchor ranges its pairs the way ``Autocalibration/*/ss_init_main.c`` does:
in the firmware's counter-clockwise order, one pair after the other through the round (a moving
team's pairs see different instants), a poll without an answer holding the channel for the
initiator's RX timeout. The order below is copied from the firmware source, not from our code."""

import numpy as np
import pytest

from uwb_env.config import SimConfig
from uwb_env.hardware.emulator import TiersAnchorDevice
from uwb_env.hardware.tiers import RX_TIMEOUT_S, RangeMatrixMessage, TiersDecoder, firmware_pair_order
from uwb_env.sim.calibration_round import RoundTiming

# ss_init_main.c: "Set the target responder in counter-clockwise order", IDs 1-based
FIRMWARE_ORDER_IDS = [(1, 4), (1, 3), (1, 2), (2, 1), (2, 4), (2, 3), (3, 2), (3, 1), (3, 4), (4, 3), (4, 2), (4, 1)]


class _World:
    def __init__(self, config):
        self.timing = RoundTiming.fit(config.calibration)


class _MovingScene:
    """Anchor 1 drives along +y at ``speed`` m/s from t = 0 (the device's clock); noise-free
    ranges, a poll unanswered with probability ``dropout``."""

    def __init__(self, speed=0.0, dropout=0.0, seed=0):
        self.config = SimConfig.from_dict({"ranging": {"dropout_probability": dropout}})
        self.world = _World(self.config)
        self.speed, self.dropout = speed, dropout
        self.rng = np.random.default_rng(seed)
        self.now = 0.0
        self.calls = 0

    def anchors_true(self):
        return np.array([[0.0, 0.0], [4.0, self.speed * self.now], [4.0, 4.0], [0.0, 4.0]])

    def measure(self, a, b, k, unbiased=False, rng=None):
        self.calls += k
        d = np.full(k, float(np.linalg.norm(np.asarray(a) - np.asarray(b))))
        d[self.rng.random(k) < self.dropout] = np.nan
        return d


def _run_round(scene, device, tick_s=0.002, limit_s=30.0):
    """Send S, poll every tick until the matrix is printed; returns (matrix, seconds)."""
    device.receive(b"S", 0.0)
    out = b""
    t = 0.0
    while t < limit_s:
        t += tick_s
        scene.now = t
        out += device.poll(t)
        found = [m for m in TiersDecoder().feed(out) if isinstance(m, RangeMatrixMessage)]
        if found:
            return found[0], t
    raise AssertionError("no matrix")


def test_pairs_are_ranged_in_the_firmware_order_at_evenly_spaced_moments():
    assert [(i + 1, j + 1) for i, j in firmware_pair_order()] == FIRMWARE_ORDER_IDS
    scene = _MovingScene()
    device = TiersAnchorDevice(scene, k=5)
    _, seconds = _run_round(scene, device)
    nominal = RoundTiming.fit(scene.config.calibration).duration_s(4, 5)
    assert [(i + 1, j + 1) for i, j, _ in device.pair_log] == FIRMWARE_ORDER_IDS
    starts = np.array([t for _, _, t in device.pair_log])
    assert np.allclose(starts, np.arange(12) * nominal / 12)
    assert seconds == pytest.approx(nominal, abs=0.005)
    # the timeout that spaces the pairs is near the firmware's RX timeout (60 ms vs 66.7 ms): the two
    # measured round lengths (K = 5 and 50) both give it
    poll_s, timeout_s = device._pair_timing()
    assert timeout_s == pytest.approx(RX_TIMEOUT_S, rel=0.15)


def test_a_moving_anchor_is_ranged_where_it_is_when_its_pair_comes_up():
    """Anchor 1 (ID 2) moves at 1 m/s. ID 1 ranges it in the third slot, ID 2 ranges ID 1 in
    the fourth, ID 3 ranges ID 2 in the seventh, ID 4 ranges ID 2 in the eleventh: the four
    cells hold four different distances, each the one at its pair's moment (the old emulator
    ranged every pair at the round's end)."""
    scene = _MovingScene(speed=1.0)
    device = TiersAnchorDevice(scene, k=5)
    matrix, seconds = _run_round(scene, device)
    mean = matrix.mean_m
    start = {(i, j): t for i, j, t in device.pair_log}

    def dist(i, j, t):
        scene.now = t
        p = scene.anchors_true()
        return np.linalg.norm(p[i] - p[j])

    for i, j in ((0, 1), (1, 0), (2, 1), (3, 1)):
        assert mean[i, j] == pytest.approx(dist(i, j, start[i, j]), abs=0.011)  # cm truncation + one tick
    assert mean[3, 1] - mean[0, 1] > 0.5  # the end of the round is 0.6 m further on for ID 4


def test_unanswered_polls_cost_the_rx_timeout_and_every_cell_averages_k_answers():
    scene = _MovingScene(dropout=0.3, seed=4)
    device = TiersAnchorDevice(scene, k=5)
    _, seconds = _run_round(scene, device)
    nominal = RoundTiming.fit(scene.config.calibration).duration_s(4, 5)
    poll_s, timeout_s = device._pair_timing()
    # 60 answers at 30 % loss: about 26 unanswered polls, each a timeout: ~2.3 s instead of 0.9
    # (the fitted 0.9 s holds retries at the model's own 30 %: its answered poll is 0 here)
    assert seconds > nominal + 10 * timeout_s
    base = 5 * poll_s + timeout_s  # a pair without retries
    lengths = np.diff([t for _, _, t in device.pair_log])
    assert np.all(lengths >= base - 1e-9)
    assert np.all(np.isclose((lengths - base) / timeout_s, np.round((lengths - base) / timeout_s)))


def test_the_pair_timing_is_the_same_timeout_at_k_5_and_50():
    """Both measured round lengths give the same per-pair timeout (60 ms, the firmware's 66.7 ms
    RX timeout within 10 %) and the same answered poll: a clamp once left K = 50 with a 104 ms
    timeout and 0 ms polls (review)."""
    timings = []
    for k in (5, 50):
        scene = _MovingScene(dropout=0.02)
        timings.append(TiersAnchorDevice(scene, k=k)._pair_timing())
    (poll5, timeout5), (poll50, timeout50) = timings
    assert timeout5 == pytest.approx(timeout50, rel=1e-9) and poll5 == pytest.approx(poll50, rel=1e-9)
    assert timeout5 == pytest.approx(RX_TIMEOUT_S, rel=0.1) and 1e-3 < poll5 < 3e-3


def test_rounds_last_the_measured_time_on_average_with_the_default_dropouts():
    """The fitted round lengths (0.9 s at K = 5, 2.5 s at K = 50) are measured totals, retries
    included: at the default 2 % dropout the emulated rounds average them (not 2.5 + retries)."""
    for k in (5, 50):
        scene = _MovingScene(dropout=0.02, seed=k)
        device = TiersAnchorDevice(scene, k=k)
        nominal = RoundTiming.fit(scene.config.calibration).duration_s(4, k)
        lengths = []
        for _ in range(30):
            device._running, device._pair, device._pair_start_s = True, 0, 0.0
            total = sum(device._range_pair(i, j) for i, j in firmware_pair_order())
            lengths.append(total)
        assert np.mean(lengths) == pytest.approx(nominal, rel=0.06), (k, np.mean(lengths))


def test_a_pair_out_of_range_hangs_the_round_as_the_firmware_retries_forever():
    scene = _MovingScene(dropout=1.0)
    device = TiersAnchorDevice(scene, k=5)
    device.receive(b"S", 0.0)
    out = b"".join(device.poll(t) for t in np.arange(0.002, 5.0, 0.002))
    assert not [m for m in TiersDecoder().feed(out) if isinstance(m, RangeMatrixMessage)]
    assert len(device.pair_log) == 1  # stuck on the first pair


def test_a_hardware_round_running_past_its_estimate_holds_the_channel_until_it_ends():
    """Retries make real rounds longer than the timing model's estimate; the backend used to end
    the busy time at the estimate, so the step after it got a negative busy fraction (and the
    env a positive reward)."""
    from uwb_env.hardware.backend import HardwareRound, HardwareWorld
    from uwb_env.sim.calibration_round import busy_fraction

    class _Silent:
        def poll(self):
            return None  # the matrix has not arrived yet

    world = HardwareWorld.__new__(HardwareWorld)
    world.round = HardwareRound(0.0, 0.9, 4, pairs=firmware_pair_order())
    world.anchor, world.role_switching = _Silent(), False
    for step in range(1, 8):  # 0.2 s steps: the estimate ends in step 5
        world.time_s = 0.2 * step
        world._poll_round()
        assert busy_fraction(world.round, world.time_s - 0.2, world.time_s, 0.2) == pytest.approx(1.0)
    assert [(i + 1, j + 1) for i, j in zip(world.round.initiator, world.round.responder, strict=True)] \
        == FIRMWARE_ORDER_IDS


def test_a_finished_hardware_round_gives_each_pair_its_slot_for_the_carry():
    """The firmware ranges its pairs one after another, each its K polls then its F broadcast's
    timeout: the backend gives the estimator each pair's polls' mean time in the timing model's
    schedule, stretched to the round's measured duration (it used to give none, so moving
    teams' ranges were never carried to the round's midpoint; then each slot's middle, 30 ms
    after the polls)."""
    from uwb_env.hardware.backend import HardwareRound, HardwareWorld
    from uwb_env.sim.round_path import pair_mean_times_s

    matrix = np.full((4, 4), 5.0)
    np.fill_diagonal(matrix, 0.0)

    class _Answers:
        def poll(self):
            return RangeMatrixMessage(mean_m=matrix, std_m=np.full((4, 4), 0.02))

    world = HardwareWorld.__new__(HardwareWorld)
    world.config = SimConfig()
    world.timing = RoundTiming.fit(world.config.calibration)
    world.means_unwrapped = world.means_wrap_ambiguous = 0
    world.round = HardwareRound(1.0, 0.9, 4, pairs=firmware_pair_order())
    world.anchor, world.role_switching = _Answers(), False
    world.time_s = 2.2  # the matrix arrives 1.2 s after the start byte (retries)
    world._poll_round()
    rnd = world.round
    assert rnd.done and rnd.times_s is not None
    # 12 slots of 0.1 s (the nominal 75 ms stretched by 1.2 / 0.9), in order; each pair's five
    # polls take the first 15 ms of its nominal slot (mean at 3 exchanges), the rest is the timeout
    stretch = 1.2 / 0.9
    polls_mean = 3 * world.timing.exchange_s * stretch
    np.testing.assert_allclose(rnd.times_s, 1.0 + np.arange(12) * 0.1 + polls_mean)
    times = pair_mean_times_s(4, rnd.times_s, rnd.initiator, rnd.responder)
    first, last = firmware_pair_order()[0], firmware_pair_order()[-1]
    assert times[first] == pytest.approx(1.0 + polls_mean) and times[last] == pytest.approx(2.1 + polls_mean)


def _static_scene(seed=0):
    from uwb_env.hardware.emulator import Scene

    cfg = SimConfig.from_dict({"anchor_motion": {"model": "static"}, "tag_motion": {"model": "static"}})
    return Scene(cfg, seed=seed, speedup=0.0)


def _round_at(device, t):
    """Send S and poll until the matrix (or give up after 5 s: a hung round); returns (message, t)."""
    decoder = TiersDecoder()
    device.receive(b"S", t)
    for _ in range(1000):
        t += 0.005
        for m in decoder.feed(device.poll(t)):
            if isinstance(m, RangeMatrixMessage):
                device.poll(t + 0.1)  # past the settle: "Waiting for Start order", as a driver waits for
                return m, t + 0.1
    return None, t


def test_a_missed_hand_over_broadcast_hangs_the_round_for_good():
    """ss_resp_run: a responder becomes initiator only on the F frame its predecessor addresses
    to it, and nothing retries that frame: missing it leaves nobody initiating."""
    from uwb_env.hardware.emulator import Faults

    device = TiersAnchorDevice(_static_scene(), faults=Faults(missed_f_probability=1.0))
    message, t = _round_at(device, 0.0)
    assert message is None and device.hung == 1
    assert [i for i, _, _ in device.pair_log] == [0, 0, 0]  # ID 1's pairs, then its F to ID 2 is lost
    device.receive(b"S", t)  # the flag is latched: another S changes nothing
    assert device.poll(t + 5.0) == b""


def test_missed_finish_broadcasts_reprint_old_cells_and_every_one_is_flagged():
    """ID 1 prints its own copy of the matrix, the other initiators' cells written from their F
    broadcasts: a missed one reprints the earlier round's cell. Every such cell repeats the
    previous matrix byte for byte, so ``repeated_cells`` flags it (besides chance repeats)."""
    from uwb_env.hardware.emulator import Faults
    from uwb_env.hardware.tiers import repeated_cells

    device = TiersAnchorDevice(_static_scene(1), faults=Faults(missed_f_probability=0.05), seed=4)
    previous, t = None, 0.0
    printed = stale_printed = flagged = 0
    off = ~np.eye(4, dtype=bool)
    for _ in range(120):
        before = device.stale_cells
        message, t = _round_at(device, t)
        if message is None:  # a hand-over was missed: only a reboot helps (it clears the cells)
            device.reboot()
            device.poll(t)
            previous = None
            continue
        fresh = device.stale_cells - before
        repeated = repeated_cells(previous, message)
        if previous is not None:  # after a reboot a missed cell is 0: never filled, not stale
            stale_printed += fresh
            flagged += int(repeated[off].sum())
            assert repeated[off].sum() >= fresh
        printed += 1
        previous = message
    assert printed > 60 and stale_printed > 10
    assert flagged - stale_printed < 0.05 * printed * 12  # chance repeats: a few % of cells


def test_repeated_cells_are_dropped_from_the_round_not_credited_to_it():
    from uwb_env.hardware.backend import HardwareRound, HardwareWorld

    mean = np.full((4, 4), 5.0)
    np.fill_diagonal(mean, 0.0)
    repeated = np.zeros((4, 4), dtype=bool)
    repeated[2, 1] = True

    class _Answers:
        def poll(self):
            return RangeMatrixMessage(mean_m=mean, std_m=np.full((4, 4), 0.02), repeated=repeated)

    world = HardwareWorld.__new__(HardwareWorld)
    world.config = SimConfig()
    world.timing = RoundTiming.fit(world.config.calibration)
    world.means_unwrapped = world.means_wrap_ambiguous = world.stale_cells_dropped = 0
    world.round = HardwareRound(0.0, 0.9, 4, pairs=firmware_pair_order())
    world.anchor, world.role_switching = _Answers(), False
    world.time_s = 1.0
    world._poll_round()
    matrix = world.round.result()
    assert np.isnan(matrix.mean_m[2, 1]) and matrix.count[2, 1] == 0
    assert matrix.mean_m[1, 2] == 5.0  # the reverse direction still has the pair
    assert world.stale_cells_dropped == 1
