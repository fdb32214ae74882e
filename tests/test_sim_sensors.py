"""Emulated sensors: the Razor IMU's text protocol and the laser's scan source."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.common.motor_units import MotorUnits
from services.common.world import World
from services.sim.razor import RazorImu
from services.sim.robot_model import SwerveRobot
from services.sim.scan_source import ScanSource


def parse_ypr(line: bytes) -> tuple[float, float, float]:
    assert line.startswith(b"#YPR=") and line.endswith(b"\r\n")
    yaw, pitch, roll = (float(v) for v in line[5:-2].split(b","))
    return yaw, pitch, roll


def test_razor_yaw_is_clockwise_degrees_and_drifts_with_bias() -> None:
    imu = RazorImu(gyro_bias_radps=0.001, gyro_noise_radps=0.0)
    for _ in range(50):  # 1 s turning counter-clockwise at 0.5 rad/s
        imu.integrate(0.5, 0.02)
    yaw, pitch, roll = parse_ypr(imu.due_frame())
    assert yaw == pytest.approx(-math.degrees(0.501), abs=0.01)
    assert (pitch, roll) == (0.0, 0.0)
    for _ in range(500):  # standing still for 10 s: only the bias integrates
        imu.integrate(0.0, 0.02)
    assert parse_ypr(imu.line())[0] == pytest.approx(-math.degrees(0.501 + 0.01), abs=0.01)
    noisy1 = RazorImu(gyro_noise_radps=0.01, seed=4)
    noisy2 = RazorImu(gyro_noise_radps=0.01, seed=4)
    for _ in range(10):
        noisy1.integrate(0.0, 0.02)
        noisy2.integrate(0.0, 0.02)
    assert noisy1.yaw_rad == noisy2.yaw_rad != 0.0


def test_razor_commands() -> None:
    imu = RazorImu()
    assert imu.due_frame() is not None  # streams at power-up
    assert imu.feed(b"#o0") == b""
    assert imu.due_frame() is None
    imu.feed(b"#f")
    assert imu.due_frame().startswith(b"#YPR=")
    assert imu.due_frame() is None
    assert imu.feed(b"#s") == b""  # split across reads
    assert imu.feed(b"ab") == b"#SYNCHab\r\n"
    imu.feed(b"#ox#o1")
    imu.integrate(0.25, 0.02)
    line = imu.due_frame()
    assert line.startswith(b"#YPRAG=")
    fields = [float(v) for v in line[7:-2].split(b",")]
    assert len(fields) == 9 and fields[5] == 256.0 and fields[8] == pytest.approx(-0.25)
    imu.feed(b"#ot")
    assert imu.due_frame().startswith(b"#YPR=")


def make_source(world: World, noise: float = 0.0) -> tuple[ScanSource, SwerveRobot]:
    robot = SwerveRobot([(0.445, 0.445), (-0.445, -0.445)], MotorUnits())
    clock = [12.5]
    return ScanSource(world, robot, lambda: clock[0], (0.45, 0.1, 0.2), 20.0, noise, seed=1), robot


def test_scan_source_casts_from_the_laser_mount() -> None:
    world = World.load_builtin("empty_room")  # walls at x = +-5, y = +-4
    source, robot = make_source(world)
    robot.teleport(0.0, 0.0, math.pi / 2)
    x, y, th = source.laser_pose()
    assert (x, y, th) == pytest.approx((-0.1, 0.45, math.pi / 2 + 0.2))
    stamp, ranges = source.laser_ranges(np.array([-0.2, math.pi / 2 - 0.2]))
    assert stamp == 12.5
    assert ranges[0] == pytest.approx(4.0 - 0.45, abs=1e-6)  # straight up to y = 4
    assert ranges[1] == pytest.approx(5.0 - 0.1, abs=1e-6)  # to the west wall at x = -5
    angles = np.linspace(-3 * math.pi / 4, 3 * math.pi / 4, 541)
    _, ranges = source.laser_ranges(angles)
    assert np.array_equal(ranges, world.raycast(x, y, angles + th, 20.0))


def test_scan_source_noise_max_range_and_dynamic_obstacles() -> None:
    world = World.load_builtin("loop")
    source, robot = make_source(world, noise=0.01)
    robot.teleport(1.5, 1.5, 0.0)
    angles = np.linspace(-3 * math.pi / 4, 3 * math.pi / 4, 541)
    clean = world.raycast(*source.laser_pose()[:2], angles + source.laser_pose()[2], 20.0)
    _, noisy = source.laser_ranges(angles)
    hit = clean < 20.0
    err = noisy[hit] - clean[hit]
    assert 0.005 < err.std() < 0.015 and abs(err.mean()) < 0.003
    assert np.array_equal(noisy[~hit], clean[~hit])
    forward = np.array([-0.2])  # laser yaw 0.2 on the robot: this beam points along +x of the world
    before = source.laser_ranges(forward)[1][0]
    world.set_obstacle("cart", None)  # [8.0, 0.0, 8.6, 1.0]
    robot.teleport(1.5, 0.5, 0.0)
    after = source.laser_ranges(forward)[1][0]
    assert after == pytest.approx(8.0 - (1.5 + 0.45), abs=0.05) and after < before  # laser at x = 1.95
