"""Issue 3 acceptance: a test-side TCP client logs in to the simulator's emulated LMS111, streams LMDscandata, and
the decoded ranges agree with ray-casting the world at the ground-truth pose."""

from __future__ import annotations

import asyncio
import math
import time

import numpy as np
import pytest

from proto import codec
from proto.messages import GroundTruth
from services.common.robot import RobotSpec
from services.lidar.cola import cmd_login, cmd_method, cmd_stream
from services.lidar.link import ColaLink, LinkLost
from services.lidar.telegrams import decode_method_result, decode_scandata
from tests.support.waiting import wait_for, wait_for_sync

pytestmark = pytest.mark.integration

SIM_NOISE_M = 0.012 + 0.01  # the scan source's noise plus the emulator's, as an upper bound on sigma
MAX_RANGE_M = 20.0


async def connect_when_listening(port: int, timeout_s: float = 20.0) -> ColaLink:
    """The sim's health token comes up before its LMS111 listens: retry the connection until the deadline."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            return await ColaLink.connect("127.0.0.1", port, connect_timeout_s=2, reply_timeout_s=5,
                                          max_telegram_bytes=65536)
        except LinkLost:
            if time.monotonic() > deadline:
                raise AssertionError(f"the emulated LMS111 never listened on port {port}") from None
            await asyncio.sleep(0.1)


async def test_emulated_lms111_streams_the_world_seen_from_the_ground_truth_pose(stack_factory):
    from services.common.world import load_world  # the simulator's own world, as the ground truth

    stack = stack_factory(services=["sim"], world="corridor").start()
    session = stack.session()
    truth: list[GroundTruth] = []
    sub = session.declare_subscriber(stack.keys("sim/ground_truth"),
                                     lambda s: truth.append(codec.decode("sim/ground_truth", s.payload.to_bytes())))
    link = await connect_when_listening(stack.lidar_port)
    try:
        assert decode_method_result(await link.request(cmd_login()), "SetAccessMode") == 1
        assert decode_method_result(await link.request(cmd_method("Run")), "Run") == 1
        assert (await link.request(cmd_stream(True))).kind == "sEA"
        scans = []
        while len(scans) < 10:
            reply = await link.next_reply(5.0)
            assert reply is not None, "no streamed scan within 5 s"
            if reply.name == "LMDscandata":
                scans.append(decode_scandata(reply))
        assert all(s.streamed for s in scans)
        counters = [s.scan_counter for s in scans]
        assert counters == sorted(counters)
    finally:
        link.close()
        sub.undeclare()
    await wait_for(lambda: truth, timeout_s=5, message="no sim/ground_truth")
    pose = truth[-1].pose  # nothing drives the robot: the pose is the same for every scan
    assert not truth[-1].collided
    world = load_world("corridor")
    spec = RobotSpec()
    lx = pose.x + math.cos(pose.theta) * spec.laser_mount_x_m - math.sin(pose.theta) * spec.laser_mount_y_m
    ly = pose.y + math.sin(pose.theta) * spec.laser_mount_x_m + math.cos(pose.theta) * spec.laser_mount_y_m
    scan = scans[-1]
    dist = scan.channel("DIST1")
    assert dist.values.size == 541 and dist.start_angle_raw == -450000 and dist.step_raw == 5000
    beams = np.radians(dist.start_angle_raw / 1e4 - 90.0 + dist.step_raw / 1e4 * np.arange(dist.values.size))
    world.apply_schedule(truth[-1].stamp)
    expected = world.raycast(lx, ly, beams + pose.theta + spec.laser_mount_theta_rad, MAX_RANGE_M)
    measured = dist.values * dist.scale / 1000.0
    no_echo = dist.values == 0
    assert np.all(no_echo[expected >= MAX_RANGE_M])  # nothing within range: no echo on the wire
    assert not np.any(no_echo[expected < MAX_RANGE_M - 5 * SIM_NOISE_M])
    hit = ~no_echo & (expected < MAX_RANGE_M)
    err = np.abs(measured[hit] - expected[hit])
    assert hit.sum() > 100
    assert np.median(err) < 2 * SIM_NOISE_M
    assert np.mean(err < 5 * SIM_NOISE_M) > 0.98


@pytest.mark.parametrize("frequency", [25, 50])
def test_zagv_up_sim_publishes_scan_at_the_configured_rate(stack_factory, frequency):
    """``zagv up --sim`` with the lidar service: ``scan`` at 25 Hz, or 50 Hz when configured (rate from the stamps,
    which are on the simulated clock; each scan decodes to 541 beams of the world)."""
    stack = stack_factory(services=["sim", "lidar"], extra_args=["--set", f"lidar.frequency_hz={frequency}"]).start()
    session = stack.session()
    got = []
    sub = session.declare_subscriber(stack.keys("scan"),
                                     lambda s: got.append(codec.decode("scan", s.payload.to_bytes())))
    try:
        wait_for_sync(lambda: len(got) >= 3 * frequency, timeout_s=60, message="too few scans:\n"
                      + stack.output()[-3000:])
    finally:
        sub.undeclare()
    window = got[-2 * frequency:]
    period = float(np.median(np.diff([m.stamp for m in window])))
    assert period == pytest.approx(1.0 / frequency, rel=0.05)
    last = window[-1]
    ranges = np.frombuffer(last.ranges, "<f4")
    assert last.frame == "laser" and ranges.size == 541 and np.isfinite(ranges).mean() > 0.5
    assert last.scan_time == pytest.approx(1.0 / frequency)
