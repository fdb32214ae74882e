"""Razor IMU: line parsing into REP-103, the serial reader on a pseudo-terminal, and the simulator's IMU end to end."""

from __future__ import annotations

import math
import os
import threading
import time

import pytest

from proto import codec
from proto.messages import Imu, Odometry, Twist2D
from services.drive.imu import ImuParseError, RazorReader, parse_line
from tests.support.waiting import wait_for_sync


def test_parse_line_converts_firmware_axes_to_rep103() -> None:
    s = parse_line("#YPRAG=30.0,10.0,-5.0,0.0,0.0,256.0,0.1,0.2,-0.3\r\n")
    assert s.yaw == pytest.approx(math.radians(-30.0))  # firmware yaw is clockwise positive
    assert s.pitch == pytest.approx(math.radians(-10.0)) and s.roll == pytest.approx(math.radians(-5.0))
    assert s.linear_acceleration == pytest.approx((0.0, 0.0, 9.806))
    assert s.angular_velocity == pytest.approx((0.1, -0.2, 0.3))


@pytest.mark.parametrize("line, reason", [
    ("#YPR=1,2,3", "not a #YPRAG"),
    ("#YPRAG=1,2,3", "9 values"),
    ("#YPRAG=1,2,3,4,5,6,7,8,x", "non-numeric"),
    ("#YPRAG=1,2,3,4,5,6,7,8,nan", "non-finite"),
])
def test_parse_line_rejects_bad_lines_with_a_reason(line: str, reason: str) -> None:
    with pytest.raises(ImuParseError, match=reason):
        parse_line(line)


def test_reader_configures_the_firmware_and_streams_samples() -> None:
    master, slave = os.openpty()
    import tty

    tty.setraw(slave)
    samples = []
    reader = RazorReader(os.ttyname(slave), 57600, samples.append)
    reader.start()
    try:
        received = b""

        def got_setup() -> bool:
            nonlocal received
            import select

            while select.select([master], [], [], 0)[0]:
                received += os.read(master, 256)
            return b"#ox" in received and b"#o1" in received

        wait_for_sync(got_setup, timeout_s=5)
        os.write(master, b"garbage\r\n#YPRAG=1,2,3\r\n#YPRAG=90.0,0,0,0,0,256,0,0,0.5\r\n#SYNCH00\r\n")
        wait_for_sync(lambda: len(samples) == 1, timeout_s=5)
        assert samples[0].yaw == pytest.approx(-math.pi / 2) and samples[0].angular_velocity[2] == -0.5
        assert reader.bad_lines == 1
    finally:
        reader.stop()
        os.close(master)
        os.close(slave)


@pytest.mark.integration
def test_imu_from_the_simulator_is_published_and_fused(stack_factory, tmp_path) -> None:
    link = str(tmp_path / "razor")
    stack = stack_factory(services=["sim", "drive"], world="empty_room", speed=2.0, extra_args=[
        "--set", f'sim.imu_link="{link}"', "--set", f'drive.imu_port="{link}"',
        "--set", "drive.imu_yaw_fusion=true", "--set", "drive.imu_yaw_weight=0.5"]).start()
    session = stack.session()
    imu: list[Imu] = []
    odom: list[Odometry] = []
    lock = threading.Lock()
    for name, t, sink in (("imu", Imu, imu), ("odom", Odometry, odom)):
        key = stack.keys(name)

        def cb(sample, t=t, sink=sink, key=key) -> None:
            with lock:
                sink.append(codec.decode_as(t, sample.payload.to_bytes(), key))

        session.declare_subscriber(key, cb)
    wait_for_sync(lambda: len(imu) > 10 and odom, timeout_s=30, message="no imu messages from the drive")
    pub = session.declare_publisher(stack.keys("cmd_vel"))
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:  # turn in place, counter-clockwise
        pub.put(codec.encode(Twist2D(wz=0.4)))
        time.sleep(0.02)
        with lock:
            if odom[-1].pose.theta > 0.5:
                break
    with lock:
        last = imu[-1]
    assert last.angular_velocity[2] == pytest.approx(0.4, abs=0.05)  # REP-103: counter-clockwise positive
    assert last.frame == "imu" and last.linear_acceleration[2] == pytest.approx(9.806, abs=0.1)
    assert odom[-1].pose.theta > 0.5
