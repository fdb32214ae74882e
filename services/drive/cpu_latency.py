"""A Linux PM QoS CPU latency request, held while the drive runs.

Writing a signed 32-bit integer ``latency_us`` (native byte order) to ``/dev/cpu_dma_latency`` registers a
system-wide request: no CPU enters an idle state whose exit latency exceeds ``latency_us`` for as long as the file
stays open. Reading the device gives the strictest request in force (``NO_CPU_LATENCY_REQUEST`` when there is
none). The kernel drops the request when the file is closed, and so when the process exits: a crashed drive leaves
nothing behind.

Why the drive asks for it: a command reaches the CAN bus through several threads (the publisher's transmit task,
the drive's receive thread, the bus), and every command comes 10-20 ms after the last one, so each of them finds its
CPU idle. Leaving a deep idle state costs about 0.1 ms at the median and milliseconds in the tail (a halted virtual
CPU); with a request of 0 the idle CPUs poll instead. That is what ``cyclictest`` does while it measures, and what
tuned's latency profiles do. The price is power: an idle CPU polls rather than sleeps.
"""

from __future__ import annotations

import os
import struct
from pathlib import Path

CPU_LATENCY_DEVICE = Path("/dev/cpu_dma_latency")
#: the largest request accepted by the configuration (10 ms: longer than any idle state's exit latency)
MAX_CPU_LATENCY_US = 10_000
#: what the device reads when no request is in force (PM_QOS_CPU_LATENCY_DEFAULT_VALUE)
NO_CPU_LATENCY_REQUEST = 2_000_000_000


class CpuLatencyError(OSError):
    """The request could not be registered; the message names the device and what to do."""


class CpuLatencyRequest:
    """An open request; :meth:`close` (or the end of the process) withdraws it."""

    def __init__(self, latency_us: int, device: Path = CPU_LATENCY_DEVICE) -> None:
        if not 0 <= latency_us <= MAX_CPU_LATENCY_US:
            raise ValueError(f"CPU latency request must be in [0, {MAX_CPU_LATENCY_US}] us, got {latency_us}")
        self.latency_us = latency_us
        self.device = device
        try:
            self._fd: int | None = os.open(device, os.O_RDWR | os.O_CLOEXEC)
        except OSError as exc:
            hint = " (it needs root, or a udev rule giving the drive's user write access)" \
                if isinstance(exc, PermissionError) else ""
            raise CpuLatencyError(exc.errno, f"cannot open {device}: {exc.strerror}{hint}") from exc
        try:
            os.write(self._fd, struct.pack("=i", latency_us))
        except OSError as exc:
            self.close()
            raise CpuLatencyError(exc.errno, f"cannot write a request to {device}: {exc.strerror}") from exc

    @property
    def active(self) -> bool:
        return self._fd is not None

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def __enter__(self) -> CpuLatencyRequest:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()


def cpu_latency_in_force_us(device: Path = CPU_LATENCY_DEVICE) -> int:
    """The strictest request in force (reading the device returns it as a 32-bit integer)."""
    with open(device, "rb") as f:
        data = f.read(4)
    if len(data) != 4:
        raise CpuLatencyError(0, f"{device}: read {len(data)} bytes, expected a 32-bit integer")
    value: int = struct.unpack("=i", data)[0]
    return value
