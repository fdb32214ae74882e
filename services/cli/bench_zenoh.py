"""Zenoh transport benchmarks: latency through the router and LaserScan throughput.

Three processes on loopback: a router (``zagv router``), an echo peer (``python -m services.cli.bench_zenoh echo``)
and the measuring process. Latency: a 64 B (or 10 kB) message goes ping -> router -> echo -> router -> ping; each
reply is handled, and the next ping sent, directly on Zenoh's network thread (``Callback(indirect=False)``), so
no Python thread wake-up sits on the path. One-way latency = round trip / 2.
Throughput: LaserScan-sized messages (541 float32 ranges, msgpack) published back to back with congestion
control BLOCK; the echo peer decodes and counts them.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import threading
import time

import numpy as np
import zenoh

from proto import codec
from proto.messages import LaserScan
from services.common.bench import BenchRow
from services.common.lifetime import die_with_parent
from services.common.session import open_session
from services.common.settings import ZenohSettings

PING, PONG, SCAN, COUNT = "bench/ping", "bench/pong", "bench/scan", "bench/count"


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def echo_main(endpoint: str) -> None:
    """The echo peer: answers pings on the network thread; counts decoded scans; replies the count."""
    die_with_parent()
    session = open_session(ZenohSettings(connect=[endpoint]))
    pong = session.declare_publisher(PONG, express=True)
    scans = 0

    def on_ping(sample: zenoh.Sample) -> None:
        pong.put(sample.payload)

    def on_scan(sample: zenoh.Sample) -> None:
        nonlocal scans
        codec.decode_as(LaserScan, sample.payload.to_bytes())
        scans += 1

    def on_count(query: zenoh.Query) -> None:
        nonlocal scans
        query.reply(COUNT, str(scans).encode())
        scans = 0

    session.declare_subscriber(PING, zenoh.handlers.Callback(on_ping, indirect=False))
    session.declare_subscriber(SCAN, zenoh.handlers.Callback(on_scan, indirect=False))
    session.declare_queryable(COUNT, on_count)
    print("echo ready", flush=True)
    try:
        sys.stdin.read()  # until the parent closes our stdin
    finally:
        session.close()


class _Peers:
    """Router and echo subprocesses for one benchmark run."""

    def __enter__(self) -> _Peers:
        port = _free_port()
        self.endpoint = f"tcp/127.0.0.1:{port}"
        env = {**os.environ, "ZAGV_PARENT_PID": str(os.getpid())}
        self.router = subprocess.Popen([sys.executable, "-m", "services.cli", "router", "--listen", self.endpoint],
                                       stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=env)
        assert self.router.stdout is not None
        self.router.stdout.readline()  # "listening on ..."
        self.echo = subprocess.Popen([sys.executable, "-m", "services.cli.bench_zenoh", "echo", self.endpoint],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env)
        assert self.echo.stdout is not None
        self.echo.stdout.readline()  # "echo ready"
        self.session = open_session(ZenohSettings(connect=[self.endpoint]))
        return self

    def __exit__(self, *exc: object) -> None:
        self.session.close()
        for p in (self.echo, self.router):
            if p.stdin:
                p.stdin.close()
            p.terminate()
            try:
                p.wait(5)
            except subprocess.TimeoutExpired:
                p.kill()


def round_trips(session: zenoh.Session, size: int, n: int, timeout_s: float = 30.0) -> np.ndarray:
    """One-way latencies (s) = RTT/2 of ``n`` sequential pings of ``size`` bytes after warm-up."""
    payload = bytes(size)
    ping = session.declare_publisher(PING, express=True)
    rtts: list[float] = []
    warmup = 200
    done = threading.Event()
    sent_at = [0.0]

    def on_pong(_sample: zenoh.Sample) -> None:
        now = time.perf_counter()
        rtts.append(now - sent_at[0])
        if len(rtts) >= n + warmup:
            done.set()
            return
        sent_at[0] = time.perf_counter()
        ping.put(payload)

    sub = session.declare_subscriber(PONG, zenoh.handlers.Callback(on_pong, indirect=False))
    # routes settle: retry the first ping until an answer arrives
    deadline = time.monotonic() + timeout_s
    while not rtts and time.monotonic() < deadline:
        sent_at[0] = time.perf_counter()
        ping.put(payload)
        if done.wait(0.2) or rtts:
            break
    done.wait(max(0.0, deadline - time.monotonic()))
    sub.undeclare()
    ping.undeclare()
    return np.asarray(rtts[warmup:]) / 2.0


def scan_throughput(session: zenoh.Session, duration_s: float = 2.0) -> float:
    """Decoded LaserScan messages per second at the echo peer, publisher sending back to back."""
    ranges = np.linspace(0.5, 20.0, 541, dtype="<f4")
    payload = codec.encode(LaserScan(ranges=ranges.tobytes(), angle_min=-2.356, angle_max=2.356,
                                     angle_increment=0.00873, range_max=20.0))
    pub = session.declare_publisher(SCAN, congestion_control=zenoh.CongestionControl.BLOCK)
    list(session.get(COUNT, timeout=2.0))  # reset the counter
    end = time.perf_counter() + duration_s
    start = time.perf_counter()
    while time.perf_counter() < end:
        for _ in range(100):
            pub.put(payload)
    elapsed = time.perf_counter() - start
    count = 0
    for _ in range(20):  # let the tail arrive, then read the count
        replies = [r.ok for r in session.get(COUNT, timeout=2.0) if r.ok is not None]
        if replies:
            count += int(replies[0].payload.to_bytes())
            break
    pub.undeclare()
    return count / elapsed


def bench_zenoh() -> list[BenchRow]:
    with _Peers() as peers:
        small = round_trips(peers.session, 64, 5000)
        large = round_trips(peers.session, 10_000, 2000)
        rate = scan_throughput(peers.session)
    return [
        BenchRow("zenoh.latency_p50_us", float(np.percentile(small, 50) * 1e6), "us", "<= 100"),
        BenchRow("zenoh.latency_p99_us", float(np.percentile(small, 99) * 1e6), "us"),
        BenchRow("zenoh.latency_10k_p50_us", float(np.percentile(large, 50) * 1e6), "us"),
        BenchRow("zenoh.scan_msgs_per_s", rate, "msg/s"),
    ]


BENCHES = [("zenoh", bench_zenoh)]


if __name__ == "__main__":
    parser = argparse.ArgumentParser(prog="python -m services.cli.bench_zenoh")
    parser.add_argument("role", choices=["echo"])
    parser.add_argument("endpoint")
    a = parser.parse_args()
    echo_main(a.endpoint)
