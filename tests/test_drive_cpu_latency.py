"""The drive's PM QoS CPU latency request: its configuration, its errors, and the kernel's answer where allowed."""

from __future__ import annotations

import os
import struct
from pathlib import Path

import msgspec
import pytest

from services.drive.config import DriveConfig
from services.drive.cpu_latency import (
    CPU_LATENCY_DEVICE,
    MAX_CPU_LATENCY_US,
    NO_CPU_LATENCY_REQUEST,
    CpuLatencyError,
    CpuLatencyRequest,
    cpu_latency_in_force_us,
)


def test_config_takes_no_request_or_one_in_range() -> None:
    assert DriveConfig().cpu_latency_us is None
    assert msgspec.convert({"cpu_latency_us": 0}, DriveConfig).cpu_latency_us == 0
    for bad in (-1, MAX_CPU_LATENCY_US + 1):
        with pytest.raises(ValueError, match="drive.cpu_latency_us"):
            msgspec.convert({"cpu_latency_us": bad}, DriveConfig)
    with pytest.raises(msgspec.ValidationError, match="cpu_latency_us"):
        msgspec.convert({"cpu_latency_us": 0.5}, DriveConfig)


def test_a_device_that_cannot_be_opened_is_an_error_naming_it(tmp_path: Path) -> None:
    missing = tmp_path / "no_such_device"
    with pytest.raises(CpuLatencyError, match="no_such_device"):
        CpuLatencyRequest(0, missing)
    with pytest.raises(ValueError, match="CPU latency request"):
        CpuLatencyRequest(-5, missing)


def test_the_request_is_one_native_32_bit_integer(tmp_path: Path) -> None:
    """The kernel reads a binary s32 (or a hex string); a file in its place shows exactly what is written."""
    device = tmp_path / "device"
    device.write_bytes(b"")
    with CpuLatencyRequest(125, device) as request:
        assert request.active
    assert not request.active
    assert device.read_bytes() == struct.pack("=i", 125)
    assert cpu_latency_in_force_us(device) == 125


def test_the_kernel_holds_the_request_while_open_and_drops_it_on_close() -> None:
    if not os.access(CPU_LATENCY_DEVICE, os.W_OK):
        pytest.skip(f"{CPU_LATENCY_DEVICE} is absent or not writable here (it needs root): the kernel's side was not "
                    "checked")
    before = cpu_latency_in_force_us()
    assert before > 0, "another process already holds a 0 us request: this check cannot tell ours from it"
    request = CpuLatencyRequest(0)
    try:
        assert cpu_latency_in_force_us() == 0
    finally:
        request.close()
    assert cpu_latency_in_force_us() == before
    assert before <= NO_CPU_LATENCY_REQUEST
