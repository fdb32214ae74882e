"""Zenoh transport benchmarks: latency and LaserScan throughput between two services, per topology.

Three processes on loopback: a router (``zagv router``), an echo process (``python -m services.launch.bench_zenoh
echo``) and the measuring process, in each topology:

- ``zenoh.*`` (what ``zagv up`` runs): the router with the settings ``zagv up`` embeds, both ends with the services'
  default settings (peers: discovery through the router, data directly);
- ``zenoh.systemd.*``: the router with ``deploy/zenoh/router-loopback.json5`` and both ends with the ``[zenoh]`` table
  of ``deploy/robot.example.toml``, as the systemd units run them;
- ``zenoh.routed.*``: both ends clients (``[zenoh] mode = "client"``, the way back): every message through the
  router.

Latency: a 64 B (or 10 kB) message goes ping -> echo -> ping; each reply is handled, and the next ping sent,
directly on Zenoh's network thread (``Callback(indirect=False)``), so no Python thread wake-up sits on the path.
One-way latency = round trip / 2. Throughput: LaserScan-sized messages (541 float32 ranges, msgpack) published back
to back with congestion control BLOCK; the echo process decodes and counts them.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import threading
import time
import tomllib
from pathlib import Path

import msgspec
import numpy as np
import zenoh

from proto import codec
from proto.messages import LaserScan
from services.common.bench import BenchRow
from services.common.lifetime import die_with_parent
from services.common.ports import free_port
from services.common.session import open_session
from services.common.settings import ZenohSettings

PING, PONG, SCAN, COUNT = "bench/ping", "bench/pong", "bench/scan", "bench/count"
REPO_ROOT = Path(__file__).resolve().parents[2]
DEPLOY = REPO_ROOT / "deploy"


def topology(name: str, endpoint: str) -> tuple[list[str], ZenohSettings]:
    """(extra ``zagv router`` arguments, the two ends' settings) of a topology (module docstring)."""
    if name == "up":
        return [], ZenohSettings(connect=[endpoint])
    if name == "routed":
        return [], ZenohSettings(mode="client", connect=[endpoint])
    if name == "systemd":
        table = tomllib.loads((DEPLOY / "robot.example.toml").read_text())["zenoh"]
        settings = msgspec.convert({**table, "connect": [endpoint]}, ZenohSettings)
        return ["--config", str(DEPLOY / "zenoh" / "router-loopback.json5")], settings
    raise ValueError(f"unknown topology {name!r} (up, routed, systemd)")


def echo_main(settings_json: str) -> None:
    """The echo process: answers pings on the network thread; counts decoded scans; replies the count."""
    die_with_parent()
    session = open_session(msgspec.json.decode(settings_json, type=ZenohSettings))
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
    """Router and echo subprocesses for one benchmark run in one topology."""

    def __init__(self, name: str = "up") -> None:
        self.name = name

    def __enter__(self) -> _Peers:
        port = free_port()
        self.endpoint = f"tcp/127.0.0.1:{port}"
        router_args, settings = topology(self.name, self.endpoint)
        env = {**os.environ, "ZAGV_PARENT_PID": str(os.getpid())}
        self.router = subprocess.Popen([sys.executable, "-m", "services.cli", "router", "--listen", self.endpoint,
                                        *router_args], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=env,
                                       cwd=REPO_ROOT)
        assert self.router.stdout is not None
        self.router.stdout.readline()  # "listening on ..."
        self.echo = subprocess.Popen([sys.executable, "-m", "services.launch.bench_zenoh", "echo",
                                      msgspec.json.encode(settings).decode()],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env, cwd=REPO_ROOT)
        assert self.echo.stdout is not None
        self.echo.stdout.readline()  # "echo ready"
        self.session = open_session(settings)
        if settings.mode == "peer":  # let the direct link come up before measuring (else the first pings detour)
            deadline = time.monotonic() + 10.0
            while not list(self.session.info.peers_zid()) and time.monotonic() < deadline:
                time.sleep(0.05)
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
    rows = []
    for name, prefix in (("up", "zenoh"), ("systemd", "zenoh.systemd"), ("routed", "zenoh.routed")):
        with _Peers(name) as peers:
            small = round_trips(peers.session, 64, 5000)
            large = round_trips(peers.session, 10_000, 2000)
            rate = scan_throughput(peers.session)
            direct = len(list(peers.session.info.peers_zid())) > 0
        path = "peer to peer" if direct else "through the router"
        rows += [
            BenchRow(f"{prefix}.latency_p50_us", float(np.percentile(small, 50) * 1e6), "us",
                     f"<= 100; 64 B one way, {path}" if name == "up" else f"64 B one way, {path}"),
            BenchRow(f"{prefix}.latency_p99_us", float(np.percentile(small, 99) * 1e6), "us"),
            BenchRow(f"{prefix}.latency_10k_p50_us", float(np.percentile(large, 50) * 1e6), "us"),
            BenchRow(f"{prefix}.scan_msgs_per_s", rate, "msg/s"),
        ]
    return rows


BENCHES = [("zenoh", bench_zenoh)]


if __name__ == "__main__":
    parser = argparse.ArgumentParser(prog="python -m services.launch.bench_zenoh")
    parser.add_argument("role", choices=["echo"])
    parser.add_argument("settings", help="the session's ZenohSettings as JSON")
    a = parser.parse_args()
    echo_main(a.settings)
