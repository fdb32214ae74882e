"""The lidar service as a process (``python -m services.lidar``) against the emulated LMS111, on a loopback router:
``scan`` at the configured rate with the room's ranges, and a reconnect after the scanner goes away."""

from __future__ import annotations

import asyncio
import contextlib
import math
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from proto.keys import Keys
from proto.messages import LaserScan, Pose2D
from services.common.clock import WallClock
from services.common.node import Node
from services.common.session import open_session
from services.common.settings import ZenohSettings
from services.sim.lms111 import Lms111Emulator
from tests.support.stack import free_port as new_free_port
from tests.support.waiting import wait_for
from tests.test_lidar_emulator import CircleRoom, check_ranges

REPO_ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.integration


@pytest.fixture
def lidar_process(router, tmp_path):
    """Start ``python -m services.lidar`` connected to the router; always stopped at teardown."""
    procs: list[subprocess.Popen] = []
    logs = []

    def start(robot_id: str, *sets: str) -> subprocess.Popen:
        argv = [sys.executable, "-m", "services.lidar", "--connect", router, "--robot-id", robot_id]
        for s in sets:
            argv += ["--set", s]
        log = open(tmp_path / f"lidar{len(procs)}.log", "wb")  # noqa: SIM115 - closed at teardown
        logs.append(log)
        env = {**os.environ, "PYTHONPATH": str(REPO_ROOT)}
        proc = subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT, cwd=REPO_ROOT, env=env,
                                start_new_session=True)
        proc.log_path = tmp_path / f"lidar{len(procs)}.log"  # type: ignore[attr-defined]
        procs.append(proc)
        return proc

    yield start
    for proc in procs:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
    for log in logs:
        log.close()


@pytest.fixture
async def scans(router):
    """A subscriber node: ``await scans(robot_id)`` returns the list the ``scan`` messages are appended to."""
    sessions, nodes = [], []

    async def subscribe(robot_id: str) -> list[LaserScan]:
        session = open_session(ZenohSettings(connect=[router]))
        sessions.append(session)
        node = Node("test", session, Keys(robot_id))
        nodes.append(node)
        got: list[LaserScan] = []
        node.subscribe("scan", got.append)
        return got

    yield subscribe
    for node in nodes:
        node.close()
    for s in sessions:
        s.close()


def log_of(proc) -> str:
    return Path(proc.log_path).read_text(errors="replace")[-3000:]


def median_period_s(msgs: list[LaserScan]) -> float:
    return float(np.median(np.diff([m.stamp for m in msgs])))


async def start_emulator(port: int, **kwargs) -> tuple[Lms111Emulator, CircleRoom]:
    clock = WallClock()
    room = CircleRoom(clock)
    emu = Lms111Emulator("127.0.0.1", port, room, clock, **kwargs)
    await emu.start()
    return emu, room


@pytest.mark.parametrize(("frequency", "extra"), [(25, ()), (50, ("lidar.intensities=true",))])
async def test_scan_on_zenoh_at_the_configured_rate(lidar_process, scans, frequency, extra):
    free_port = new_free_port()  # the router has the fixture's port
    emu, room = await start_emulator(free_port)  # powers up at 25 Hz; the service sets what it is configured to
    try:
        got = await scans(f"l{frequency}")
        proc = lidar_process(f"l{frequency}", f"lidar.port={free_port}", f"lidar.frequency_hz={frequency}", *extra)
        await wait_for(lambda: len(got) >= 2 * frequency or proc.poll() is not None, timeout_s=40,
                       message="no scans arrived")
        assert proc.poll() is None, log_of(proc)
        assert emu.frequency_raw == frequency * 100
        window = list(got[-frequency:])
        assert median_period_s(window) == pytest.approx(1.0 / frequency, rel=0.1)
        last = window[-1]
        assert last.frame == "laser" and last.mount == Pose2D(x=0.45, y=0.0, theta=0.0)  # RobotSpec default
        assert last.scan_time == pytest.approx(1.0 / frequency)
        assert last.angle_min == pytest.approx(math.radians(-135)) and last.range_max == 20.0
        assert len(last.ranges) == 541 * 4
        check_ranges(last, room, emu.range_noise_m)
        assert (len(last.intensities) == len(last.ranges)) == bool(extra)
        counters = [m.scan_counter for m in window]
        assert counters == sorted(counters) and len(set(counters)) == len(counters)
    finally:
        await emu.stop()


async def test_reconnects_after_the_scanner_restarts(lidar_process, scans):
    free_port = new_free_port()
    emu, room = await start_emulator(free_port)
    got = await scans("lr")
    proc = lidar_process("lr", f"lidar.port={free_port}", "lidar.reconnect_max_s=1.0")
    try:
        await wait_for(lambda: len(got) >= 10 or proc.poll() is not None, timeout_s=40,
                       message="no scans before the restart")
        await emu.stop()
        before = len(got)
        emu, room = await start_emulator(free_port)
        await wait_for(lambda: len(got) >= before + 25 or proc.poll() is not None, timeout_s=30,
                       message="scans did not resume after the scanner came back")
        assert proc.poll() is None, log_of(proc)
        assert got[-1].scan_counter < 200  # from the new scanner (its counters start again)
        check_ranges(got[-1], room, emu.range_noise_m)
        assert "reconnecting" in log_of(proc)
    finally:
        await emu.stop()


@pytest.fixture
async def lidar_in_process(router):
    """A LidarNode in the test's event loop (for its counters); stopped at teardown."""
    from services.lidar.config import LidarConfig
    from services.lidar.node import LidarNode

    running = []

    async def start(robot_id: str, **config) -> LidarNode:
        session = open_session(ZenohSettings(connect=[router]))
        node = Node("lidar", session, Keys(robot_id))
        lidar = LidarNode(node, LidarConfig(**config), Pose2D(x=0.3))
        stop = asyncio.Event()
        task = asyncio.get_running_loop().create_task(lidar.run(stop))
        running.append((stop, task, node, session))
        return lidar

    yield start
    for stop, task, node, session in running:
        stop.set()
        await asyncio.wait_for(task, 10)
        node.close()
        session.close()


async def test_watchdog_reconnects_when_the_scanner_stops_measuring(lidar_in_process, scans):
    from services.lidar.cola import cmd_login, cmd_method
    from services.lidar.link import ColaLink

    port = new_free_port()
    emu, room = await start_emulator(port)
    try:
        got = await scans("lw")
        lidar = await lidar_in_process("lw", port=port, watchdog_timeout_s=0.5, reconnect_min_s=0.1)
        await wait_for(lambda: len(got) >= 5, timeout_s=30, message="no scans")
        assert got[-1].mount == Pose2D(x=0.3)
        # another client stops the measurement: the stream goes silent although the connection stays up
        other = await ColaLink.connect("127.0.0.1", port, connect_timeout_s=3, reply_timeout_s=3,
                                       max_telegram_bytes=65536)
        await other.request(cmd_login())
        await other.request(cmd_method("LMCstopmeas"))
        other.close()
        await wait_for(lambda: "watchdog" in lidar.last_error, timeout_s=10, message="the watchdog did not fire")
        before = len(got)
        await wait_for(lambda: len(got) >= before + 5, timeout_s=20, message="scans did not resume")
        assert lidar.connects >= 2 and emu.measuring  # the new session started the measurement again
    finally:
        await emu.stop()


async def test_refused_login_is_reported_and_retried(lidar_in_process, scans):
    port = new_free_port()
    emu, _ = await start_emulator(port)
    try:
        got = await scans("ll")
        lidar = await lidar_in_process("ll", port=port, login_password_hash="DEADBEEF", reconnect_max_s=0.3)
        await wait_for(lambda: lidar.connects >= 3, timeout_s=20, message="no retries")
        assert "login refused" in lidar.last_error and not got
        assert lidar.node.extra_stats["lidar"]["last_error"].startswith("login refused")
    finally:
        await emu.stop()
