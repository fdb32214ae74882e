"""Swerve physics: motor units, motor control loops, least-squares body motion, SE(2) integration, collision."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.common.motor_units import MotorUnits
from services.common.robot import RobotSpec
from services.common.world import World
from services.sim.config import SimConfig
from services.sim.robot_model import (
    SlipModel,
    SteerMotor,
    SwerveRobot,
    TractionMotor,
    integrate_se2,
    lsq_twist_matrix,
)
from services.sim.simulation import Simulation

UNITS = MotorUnits(wheel_radius_m=0.1, gear_ratio=30.0, traction_counts_per_rev=4096, steer_counts_per_rev=204800,
                   steer_motor_counts_per_rev=4096, steer_zero_counts=1000)
MODULES = [(0.445, 0.445), (-0.445, -0.445)]


def test_motor_units_follow_paper_equations() -> None:
    # eq. 7: v = V * 2 pi R / (J * 60)
    assert UNITS.rpm_to_mps(1000.0) == pytest.approx(1000.0 * 2 * math.pi * 0.1 / (30.0 * 60.0))
    assert UNITS.mps_to_rpm(UNITS.rpm_to_mps(1234.0)) == pytest.approx(1234.0)
    # eq. 8: theta = (P - P0) * 2 pi / N
    assert UNITS.counts_to_rad(1000 + 51200) == pytest.approx(math.pi / 2)
    assert UNITS.rad_to_counts(-math.pi) == pytest.approx(1000 - 102400)
    # one wheel revolution = J motor revolutions = J * cpr counts = 2 pi R of travel
    assert UNITS.counts_to_m(30 * 4096) == pytest.approx(2 * math.pi * 0.1)


def test_traction_ramps_at_its_acceleration_and_counts_its_turns() -> None:
    m = TractionMotor(cpr=4096, accel_rpm_s=1000.0, decel_rpm_s=2000.0, tau_s=0.0)
    m.target_rpm = 600.0
    for _ in range(100):  # 0.5 s
        m.step(0.005)
    assert m.speed_rpm == pytest.approx(500.0, abs=1e-6)
    for _ in range(200):
        m.step(0.005)
    assert m.speed_rpm == pytest.approx(600.0)
    counts = m.position_counts
    for _ in range(200):  # 1 s at 600 rpm = 10 revolutions
        m.step(0.005)
    assert m.position_counts - counts == pytest.approx(10 * 4096)
    m.target_rpm = 0.0
    for _ in range(60):  # decel 2000 rpm/s: stopped after 0.3 s
        m.step(0.005)
    assert m.speed_rpm == pytest.approx(0.0, abs=1e-9)
    m.target_rpm = 1e9
    m.step(0.005)
    assert m.ramped_rpm <= m.max_rpm


def test_steering_profile_respects_rate_and_acceleration_and_lands_exactly() -> None:
    s = SteerMotor(cpr=4096, travel_rpm=1500.0, accel_rpm_s=5000.0, decel_rpm_s=5000.0)
    s.target_counts = 150000.0
    speeds = []
    for _ in range(600):
        s.step(0.005)
        speeds.append(s.speed_counts_s)
    assert s.position_counts == 150000.0 and s.speed_counts_s == 0.0
    v = np.array(speeds)
    assert v.max() <= 1500.0 / 60 * 4096 + 1e-6
    dv_max = 5000.0 / 60 * 4096 * 0.005
    jumps = np.abs(np.diff(v))
    settle = (v[1:] == 0.0) & (v[:-1] != 0.0)
    assert settle.sum() == 1
    assert jumps[~settle].max() <= dv_max + 1e-6
    assert jumps[settle].max() <= 2 * dv_max, "the final settle step stops from at most two steps' worth of speed"
    s.target_counts = 0.0
    for _ in range(20):
        s.step(0.005)
    s.hold()
    stop_at = s.target_counts
    for _ in range(400):
        s.step(0.005)
    assert s.position_counts == pytest.approx(stop_at, abs=1.0)


def test_integrate_se2_is_exact_for_constant_twist() -> None:
    # a full circle of radius 1 (vx = 1, wz = 1) returns to the start, whatever the step
    x, y, th = 0.0, 0.0, 0.0
    for _ in range(10):
        x, y, th = integrate_se2(x, y, th, 1.0, 0.0, 1.0, 2 * math.pi / 10)
    assert (x, y, th) == pytest.approx((0.0, 0.0, 0.0), abs=1e-12)
    # a quarter turn in one step lands on the arc
    assert integrate_se2(0.0, 0.0, 0.0, 1.0, 0.0, 1.0, math.pi / 2) == pytest.approx((1.0, 1.0, math.pi / 2))
    # sideways motion in a rotated frame
    assert integrate_se2(1.0, 2.0, math.pi / 2, 0.0, 0.5, 0.0, 2.0) == pytest.approx((0.0, 2.0, math.pi / 2))


def test_least_squares_twist_from_wheel_vectors() -> None:
    p = lsq_twist_matrix(MODULES)
    for twist in [(0.2, 0.0, 0.0), (0.0, -0.1, 0.0), (0.0, 0.0, 0.5), (0.1, 0.05, -0.3)]:
        vx, vy, wz = twist
        wheels = []
        for x, y in MODULES:
            wheels += [vx - wz * y, vy + wz * x]  # inverse kinematics (docs/architecture.md)
        assert p @ np.array(wheels) == pytest.approx(np.array(twist), abs=1e-12)


def make_robot(world: World | None = None, radius: float = 0.63, slip: SlipModel | None = None) -> SwerveRobot:
    robot = SwerveRobot(MODULES, UNITS, slip)
    for m in robot.modules:
        m.traction.tau_s = 0.0
        m.traction.accel_rpm_s = m.traction.decel_rpm_s = 1e6
    if world is not None:
        robot.margin = lambda x, y: world.clearance_m(x, y) - radius
    return robot


def drive(robot: SwerveRobot, speed_mps: float, steer_rad: float, seconds: float, dt: float = 0.005) -> None:
    for m in robot.modules:
        m.traction.target_rpm = UNITS.mps_to_rpm(speed_mps)
        m.steer.target_counts = UNITS.rad_to_counts(steer_rad)
    for _ in range(round(seconds / dt)):
        robot.step(dt)


def test_modules_driven_alike_translate_the_body() -> None:
    robot = make_robot()
    drive(robot, 0.0, math.pi / 2, 1.0)  # steer first
    drive(robot, 0.2, math.pi / 2, 2.0)
    assert (robot.x, robot.y, robot.theta) == pytest.approx((0.0, 0.4, 0.0), abs=1e-3)
    assert robot.vy == pytest.approx(0.2) and robot.wz == pytest.approx(0.0, abs=1e-12)


def test_opposed_modules_turn_in_place() -> None:
    robot = make_robot()
    # wheel i velocity for wz: (-wz*y_i, wz*x_i): both along 135 deg (opposite senses), speed wz*|r_i|
    drive(robot, 0.0, 3 * math.pi / 4, 1.0)
    drive(robot, 0.5 * math.hypot(0.445, 0.445), 3 * math.pi / 4, 0.0)
    robot.modules[1].traction.target_rpm = -robot.modules[1].traction.target_rpm
    for _ in range(200):
        robot.step(0.005)
    assert robot.wz == pytest.approx(0.5)
    assert math.hypot(robot.x, robot.y) < 1e-9
    assert robot.theta == pytest.approx(0.5, abs=1e-3)


def test_slip_shortens_the_ground_travel_but_not_the_counts() -> None:
    robot = make_robot(slip=SlipModel(slip_ratio=0.1))
    drive(robot, 0.2, 0.0, 2.0)
    travelled = UNITS.counts_to_m(robot.modules[0].traction.position_counts)
    assert travelled == pytest.approx(0.4, abs=1e-3)
    assert robot.x == pytest.approx(0.36, abs=1e-3)
    noisy = SlipModel(slip_ratio=0.0, slip_noise=0.05, seed=3)
    again = SlipModel(slip_ratio=0.0, slip_noise=0.05, seed=3)
    assert [noisy.factor() for _ in range(5)] == [again.factor() for _ in range(5)]


def test_collision_stops_the_robot_and_latches_until_teleport() -> None:
    world = World.load_builtin("empty_room")  # walls at x = +-5
    robot = make_robot(world)
    robot.teleport(3.5, -2.0, 0.0)
    drive(robot, 0.5, 0.0, 6.0)
    assert robot.collided
    assert robot.x == pytest.approx(5.0 - 0.63, abs=0.06)
    assert robot.vx == 0.0
    x_stop = robot.x
    drive(robot, -0.2, 0.0, 1.0)  # backing away is allowed
    assert robot.x < x_stop - 0.1 and robot.collided
    robot.teleport(0.0, 0.0, 0.0)
    assert not robot.collided


def test_simulation_publishes_consistent_encoders_and_imu() -> None:
    cfg = SimConfig(world="empty_room", imu_gyro_noise_radps=0.0, imu_gyro_bias_radps=0.0)
    sim = Simulation(cfg, RobotSpec(), World.load_builtin("empty_room"))
    assert [f[0] for f in sim.boot()] == [0x701, 0x702]
    # command through SDO as a master would: node 1 and 2 traction 100 per mille (300 rpm), steering 0
    for n in (1, 2):
        sim.on_can_frame(0x600 + n, bytes([0x23, 0x00, 0x20, 0x01]) + (100).to_bytes(4, "little"))
    frames = []
    for _ in range(400):
        frames += sim.step()
    assert sim.now_s == pytest.approx(2.0)
    assert sim.robot.x > 0.1 and abs(sim.robot.y) < 1e-9
    counts = sim.nodes[0].counter(1)
    assert UNITS.counts_to_m(counts) == pytest.approx(sim.robot.x, abs=1e-3)
    assert {cid for cid, _ in frames} == {0x701, 0x702}, "heartbeats only before NMT start"
    assert sim.imu.line() == b"#YPR=-0.00,0.00,0.00\r\n" or sim.imu.line() == b"#YPR=0.00,0.00,0.00\r\n"
    assert not sim.teleport(math.nan, 0.0, 0.0)
    assert sim.teleport(1.0, 1.0, 0.5) and (sim.robot.x, sim.robot.y, sim.robot.theta) == (1.0, 1.0, 0.5)


@pytest.mark.parametrize(("override", "message"), [
    ({"step_s": 0.0}, "step_s"), ({"node_ids": [1, 1]}, "node_ids"), ({"start_pose": [1.0]}, "start_pose"),
    ({"steer_zero_counts": [0]}, "steer_zero_counts"), ({"slip_ratio": 1.5}, "slip_ratio"),
])
def test_bad_sim_config_is_named(override: dict, message: str) -> None:
    import msgspec

    cfg = msgspec.structs.replace(SimConfig(), **override)
    with pytest.raises(ValueError, match=message):
        Simulation(cfg, RobotSpec(), World.load_builtin("empty_room"))
