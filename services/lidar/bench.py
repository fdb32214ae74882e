"""Benchmarks: ``lidar.parse_us`` (one 541-point LMDscandata telegram -> LaserScan) and stream framing."""

from __future__ import annotations

import functools

import numpy as np

from proto.messages import Pose2D
from services.common.bench import BenchRow, time_calls
from services.lidar.cola import FrameParser, parse_reply
from services.lidar.convert import to_laserscan
from services.lidar.telegrams import decode_scandata


def scan_telegram(points: int = 541, *, rssi: bool = False, seed: int = 0) -> bytes:
    """A realistic streamed telegram (payload without STX/ETX): 50 Hz, 0.5 deg, DIST1 (+ 16-bit RSSI1)."""
    rng = np.random.default_rng(seed)
    values = rng.integers(0, 20000, points)
    head = "sSN LMDscandata 1 1 89A27F 0 0 343 347 27477BA9 2747813B 0 0 7 0 0 1388 168 0"
    block = f"3F800000 00000000 FFF92230 1388 {points:X} "
    channels = ["DIST1 " + block + " ".join(format(v, "X") for v in values)]
    if rssi:
        channels.append("RSSI1 " + block + " ".join(format(v, "X") for v in rng.integers(0, 60000, points)))
    tail = "0 0 1 6 LMS111 0 1 7E8 5 14 C 1E 2D 7A120 0"
    return f"{head} {len(channels)} {' '.join(channels)} {tail}".encode("ascii")


def decode(payload: bytes, intensities: bool = False):  # LaserScan
    scan = decode_scandata(parse_reply(payload))
    return to_laserscan(scan, stamp=0.0, range_min_m=0.05, range_max_m=20.0, mount=Pose2D(), intensities=intensities)


def bench_parse() -> list[BenchRow]:
    rows = []
    for name, points, rssi in (("parse_us", 541, False), ("parse_1081_rssi_us", 1081, True)):
        payload = scan_telegram(points, rssi=rssi)
        t = time_calls(functools.partial(decode, payload, rssi), repeat=2000, max_s=5.0)
        goal = "<= 200" if name == "parse_us" else ""
        rows.append(BenchRow(f"lidar.{name}", float(np.median(t) * 1e6), "us", goal))
    framed = b"\x02" + scan_telegram(541) + b"\x03"
    chunks = [framed[i:i + 1448] for i in range(0, len(framed), 1448)]  # TCP-segment-sized reads
    parser = FrameParser()

    def frame_all() -> None:
        for c in chunks:
            parser.feed(c)

    t = time_calls(frame_all, repeat=2000, max_s=3.0)
    rows.append(BenchRow("lidar.frame_us", float(np.median(t) * 1e6), "us", ""))
    return rows


BENCHES = [("lidar", bench_parse)]
