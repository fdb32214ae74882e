"""Loopback ports for tests, benches and ``zagv up`` when a port is left to choose."""

from __future__ import annotations

import random
import socket
import time
from pathlib import Path


def _ephemeral_range() -> tuple[int, int]:
    """The kernel's range for port-0 binds and outgoing connections (Linux ``ip_local_port_range``)."""
    try:
        low, high = (int(v) for v in Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split())
        return low, high
    except (OSError, ValueError):
        return 32768, 60999


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago, chosen below the kernel's ephemeral range: a port handed
    out now and bound later (``zagv up``'s HTTP, CAN and lidar ports) is then never taken in between by a port-0
    bind or an outgoing connection of another process (a Zenoh peer listens on port 0). Falls back to a port-0 bind
    when no such port is free."""
    low, _ = _ephemeral_range()
    start = max(1024, low - 12000)
    rng = random.SystemRandom()
    for _ in range(200):
        port = rng.randrange(start, low) if low > start else 0
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
            return int(s.getsockname()[1])
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
