"""Loopback ports for tests, benches and ``zagv up`` when a port is left to choose.

A port chosen here is handed to another process, which binds it a moment later. Meanwhile any listener that binds
port 0 (every Zenoh peer does) or any outgoing connection gets a port from the kernel's ephemeral range. A port
chosen from that same range can be taken in between. So ``free_port`` picks outside it: ports below the range's
low end (Linux: ``/proc/sys/net/ipv4/ip_local_port_range``, 32768–60999 by default), which the kernel never hands
out on its own.
"""

from __future__ import annotations

import random
import socket
import time
from pathlib import Path

EPHEMERAL_RANGE_FILE = Path("/proc/sys/net/ipv4/ip_local_port_range")
LOWEST_CHOSEN_PORT = 10_000
"""Stay above the ports well-known services listen on (e.g. 7447 Zenoh, 1883 MQTT, 8080 HTTP)."""


def ephemeral_range() -> tuple[int, int]:
    """The kernel's ephemeral port range (low, high), or IANA's 49152–65535 where the kernel does not say."""
    try:
        low, high = (int(v) for v in EPHEMERAL_RANGE_FILE.read_text().split())
        return low, high
    except (OSError, ValueError):
        return 49152, 65535


def candidate_ranges(low: int, high: int) -> list[range]:
    """The port ranges outside [low, high] and above ``LOWEST_CHOSEN_PORT``, widest first."""
    ranges = [range(LOWEST_CHOSEN_PORT, low), range(high + 1, 65536)]
    return sorted((r for r in ranges if len(r) >= 100), key=len, reverse=True)


def bindable(port: int, host: str = "127.0.0.1") -> bool:
    """True when ``host:port`` can be bound for TCP right now."""
    with socket.socket() as s:
        try:
            s.bind((host, port))
        except OSError:
            return False
        return True


def free_port(rng: random.Random | None = None) -> int:
    """A TCP port on 127.0.0.1 that is free now and outside the ephemeral range, so no port-0 bind can take it
    before its user binds it. Falls back to a kernel-chosen port when no such range is wide enough."""
    rng = rng or random.SystemRandom()
    ranges = candidate_ranges(*ephemeral_range())
    if ranges:
        for _ in range(200):
            port = rng.choice(ranges[0])
            if bindable(port):
                return port
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_listening(port: int, timeout_s: float, host: str = "127.0.0.1") -> None:
    """Return once ``host:port`` takes a TCP connection; raise TimeoutError naming the address after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            with socket.create_connection((host, port), timeout=0.5):
                return
        except OSError:
            if time.monotonic() > deadline:
                raise TimeoutError(f"nothing listened on {host}:{port} within {timeout_s:.1f} s") from None
            time.sleep(0.02)
