"""Hardware layer: parser throughput and one calibration round against the emulator.

Parsers: ``lec`` lines/s through the streaming shell decoder (and the bare line parser) on a
tag's stream (anchors at their configured positions, the tag moving), and the worst case of
new anchor positions on every line (no repeated anchor groups to reuse); TLV
``dwm_loc_get`` frames/s, TIERS matrices/s. End to end: the wall time of a calibration round
(``S`` to decoded matrix) over a pseudo-terminal against the emulated TIERS anchor, beside
the timing model's duration, for K = 5 and K = 50. Target: >= 100,000 lec lines/s.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._common import print_table, write_results  # noqa: E402
from uwb_env.config import SimConfig  # noqa: E402
from uwb_env.hardware import tlv  # noqa: E402
from uwb_env.hardware.drivers import TiersAnchorDriver  # noqa: E402
from uwb_env.hardware.emulator import Emulator, Scene, TiersAnchorDevice  # noqa: E402
from uwb_env.hardware.pans_shell import AnchorRange, ShellDecoder, format_lec, parse_lec  # noqa: E402
from uwb_env.hardware.tiers import TiersDecoder, encode_matrix  # noqa: E402
from uwb_env.hardware.transport import SerialTransport  # noqa: E402


def stream_lines(count: int, moving_anchors: bool, seed: int = 0) -> list[str]:
    """A tag's lec stream: 4 anchors at their configured positions (or new ones every line),
    the tag moving, distances changing every line."""
    rng = np.random.default_rng(seed)
    anchors = np.array([[5.0, 8.0, 2.25], [0.0, 8.0, 2.25], [5.0, 0.0, 2.25], [0.0, 0.0, 2.25]])
    ids = ["1151", "0CA8", "111C", "1150"]
    out = []
    for _ in range(count):
        a = anchors + rng.uniform(-3, 3, anchors.shape) if moving_anchors else anchors
        tag = np.r_[rng.uniform(0, 5, 2), 1.0]
        d = np.linalg.norm(a - tag, axis=1) + rng.normal(0, 0.05, 4)
        out.append(format_lec([AnchorRange(i, tuple(p), float(x)) for i, p, x in zip(ids, a, d, strict=True)],
                              tuple(tag), 98))
    return out


def per_second(fn, items: int, min_time_s: float) -> float:
    fn()  # warm-up: first-call costs (imports, caches) are not throughput
    done, start = 0, time.perf_counter()
    while time.perf_counter() - start < min_time_s:
        fn()
        done += items
    return done / (time.perf_counter() - start)


def round_time(k: int, rounds: int) -> tuple[float, float]:
    scene = Scene(SimConfig.from_dict({"anchor_motion": {"model": "static"}, "tag_motion": {"model": "static"}}))
    with Emulator(scene) as emu:
        url = emu.add("anchor", TiersAnchorDevice(scene, k=k))
        with SerialTransport(url) as port:
            driver = TiersAnchorDriver(port, round_timeout_s=10)
            # let the board's boot banner arrive first: a banner read after the first S now
            # (rightly) fails that round as a reboot
            time.sleep(0.3)
            times = []
            for _ in range(rounds):
                t = time.perf_counter()
                driver.run_round()
                times.append(time.perf_counter() - t)
    return float(np.median(times)), scene.world.timing.duration_s(4, k)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true")
    a = p.parse_args()
    t = 0.3 if a.quick else 2.0
    lines = stream_lines(1000, moving_anchors=False)
    block = "".join(line + "\r\n" for line in lines).encode()
    stream = per_second(lambda: ShellDecoder().feed(block), 1000, t)
    bare = per_second(lambda: [parse_lec(line) for line in lines], 1000, t)
    # worst case: every line reports new anchor positions (no repeated anchor groups)
    moving = stream_lines(1000, moving_anchors=True)
    block_moving = "".join(line + "\r\n" for line in moving).encode()
    stream_moving = per_second(lambda: ShellDecoder().feed(block_moving), 1000, t)
    anchors = [tlv.Distance(0x1150 + i, 3.0 + i, 100, tlv.Position(i, 2 * i, 2.25, 100)) for i in range(4)]
    frame = tlv.encode_location_tag(tlv.Position(1.0, 2.0, 0.5, 100), anchors)
    frames = per_second(lambda: [tlv.decode_location(tlv.parse_response(frame)) for _ in range(1000)], 1000, t)
    matrix = encode_matrix(np.full((4, 4), 5.0), np.full((4, 4), 0.02)) * 100
    matrices = per_second(lambda: TiersDecoder().feed(matrix), 100, t)
    rows = [["lec lines/s (streaming decoder)", stream], ["lec lines/s (line parser)", bare],
            ["lec lines/s, anchors moving every line (streaming)", stream_moving],
            ["TLV loc_get frames/s", frames], ["TIERS matrices/s", matrices]]
    print_table("Parser throughput", ["what", "per s"], rows)
    rounds = []
    for k in (5,) if a.quick else (5, 50):
        measured, model = round_time(k, 2 if a.quick else 5)
        rounds.append([k, measured, model, measured / model])
    print_table("Calibration round over a pty vs the timing model (4 anchors)",
                ["K", "measured s", "model s", "ratio"], rounds)
    figures = {"lec_lines_per_s": stream, "lec_lines_per_s_line_parser": bare,
               "lec_lines_per_s_moving_anchors": stream_moving, "tlv_frames_per_s": frames,
               "tiers_matrices_per_s": matrices, "lec_target_per_s": 100_000,
               "lec_target_met": stream >= 100_000}
    for k, measured, model, ratio in rounds:
        figures |= {f"round_k{k}_measured_s": measured, f"round_k{k}_model_s": model,
                    f"round_k{k}_ratio": ratio}
    write_results("bench_hardware" + ("_quick" if a.quick else ""), figures, a.quick)


if __name__ == "__main__":
    main()
