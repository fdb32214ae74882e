"""Fuzzing the stream parser and the decoders: arbitrary bytes, and valid telegrams mutated and cut into random
reads, end in a scan or a clear ``ColaError`` -- never another exception, a hang or an unbounded buffer."""

from __future__ import annotations

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from proto.messages import LaserScan, Pose2D
from services.lidar.cola import ColaError, FrameParser, FramingError, parse_reply
from services.lidar.convert import to_laserscan
from services.lidar.telegrams import decode_scancfg, decode_scandata
from tests.test_lidar_cola import EXAMPLE, build_scandata

MAX_TELEGRAM = 512
SEEDS = [
    EXAMPLE,
    build_scandata([0, 1, 0xFFFF, 500], rssi=[1, 2, 3, 255], rssi_bits=8, name="a b", time=(2024, 1, 1, 0, 0, 0, 0),
                   encoders=[(1, 2)], position=True, event=True),
    build_scandata([100] * 5, tail=False),
    b"\x02sRA LMPscancfg 1388 1 1388 FFF92230 225510\x03",
    b"\x02sAN mLMPsetscancfg 0 9C4 1 9C4 FFF92230 225510\x03\x02sFA 5\x03",
]
SPECIAL = [b"\x02", b"\x03", b" ", b"  ", b"0", b"FFFFFFFF", b"DIST1", b"RSSI1", b"\x00", b"\xff", b"1", b"9", b"+",
           b"-1", b"7FC00000", b"LMDscandata", b"sSN"]


@st.composite
def mutated_stream(draw) -> bytes:
    """1-3 valid telegrams with up to 6 random edits (insert, delete, replace, truncate); few draws, so fast."""
    rnd = draw(st.randoms(use_true_random=False))
    data = bytearray(b"".join(rnd.choice(SEEDS) for _ in range(rnd.randint(1, 3))))
    for _ in range(rnd.randint(0, 6)):
        op = rnd.choice(("insert", "delete", "replace", "truncate"))
        pos = rnd.randint(0, len(data))
        if op == "insert":
            data[pos:pos] = rnd.choice(SPECIAL) if rnd.random() < 0.7 else rnd.randbytes(rnd.randint(1, 8))
        elif op == "delete":
            del data[pos:pos + rnd.randint(1, 12)]
        elif op == "replace":
            data[pos:pos + 1] = rnd.choice(SPECIAL)
        else:
            del data[pos:]
    return bytes(data)


def chunks_of(data: bytes, cuts: list[int]) -> list[bytes]:
    points = sorted({c % (len(data) + 1) for c in cuts} | {0, len(data)})
    return [data[a:b] for a, b in zip(points, points[1:])]


def consume(payload: bytes) -> LaserScan | None:
    """What the node does with a telegram: decode it by name; ColaError is the only allowed failure."""
    reply = parse_reply(payload)
    if reply.name == "LMDscandata":
        scan = decode_scandata(reply)
        msg = to_laserscan(scan, stamp=0.0, range_min_m=0.05, range_max_m=20.0, mount=Pose2D(), intensities=True)
        ranges = np.frombuffer(msg.ranges, "<f4")
        assert not np.isnan(ranges).any()
        return msg
    if reply.name in ("LMPscancfg", "mLMPsetscancfg") or reply.kind == "sFA":
        decode_scancfg(reply)
    return None


@settings(max_examples=10_000, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.one_of(st.binary(max_size=700), mutated_stream()), cuts=st.lists(st.integers(0, 10_000), max_size=6))
def test_arbitrary_bytes_end_in_a_scan_or_a_clear_error(data: bytes, cuts: list[int]) -> None:
    parser = FrameParser(max_telegram_bytes=MAX_TELEGRAM)
    items: list[bytes | FramingError] = []
    for chunk in chunks_of(data, cuts):
        items += parser.feed(chunk)
        assert parser.buffered <= MAX_TELEGRAM
    assert len(items) <= len(data) + 1
    for item in items:
        if isinstance(item, FramingError):
            assert str(item)
            continue
        assert isinstance(item, bytes) and len(item) <= MAX_TELEGRAM and b"\x02" not in item and b"\x03" not in item
        try:
            consume(item)
        except ColaError as exc:
            assert str(exc)


def test_unmutated_seeds_decode() -> None:
    parser = FrameParser(max_telegram_bytes=MAX_TELEGRAM)
    scans = [consume(p) for seed in SEEDS for p in parser.feed(seed) if isinstance(p, bytes)
             and not p.startswith(b"sFA")]
    assert sum(isinstance(s, LaserScan) for s in scans) == 3
