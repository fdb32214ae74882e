"""Swerve kinematics core: inverse/forward kinematics, optimisation, limits, odometry, motor units."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.common.motor_units import MotorUnits
from services.common.robot import RobotSpec, TwistLimits
from services.common.se2 import wrap_angle
from services.drive.kinematics import (
    ModuleState,
    SteeringLimits,
    SwerveKinematics,
    Twist,
    cosine_scale,
    desaturate,
    optimize,
)
from services.drive.odometry import Pose, arc_pose

ROBOT = RobotSpec()
KIN = SwerveKinematics([(m.x_m, m.y_m) for m in ROBOT.modules])

speeds = st.floats(-2.0, 2.0, allow_nan=False)
angles = st.floats(-4 * math.pi, 4 * math.pi, allow_nan=False)
twists = st.builds(Twist, speeds, speeds, st.floats(-3.0, 3.0, allow_nan=False))
positions = st.lists(st.tuples(st.floats(-2, 2), st.floats(-2, 2)), min_size=2, max_size=4).filter(
    lambda ps: max(math.dist(a, b) for a in ps for b in ps) > 0.1)


def close(a: float, b: float, tol: float = 1e-9) -> bool:
    return abs(a - b) <= tol * max(1.0, abs(a), abs(b))


@given(twists)
def test_forward_of_inverse_is_identity_with_zero_residual(t: Twist) -> None:
    fk = KIN.to_twist(KIN.to_module_states(t))
    assert close(fk.twist.vx, t.vx) and close(fk.twist.vy, t.vy) and close(fk.twist.wz, t.wz)
    assert fk.residual_mps < 1e-9


@given(positions, twists)
def test_forward_of_inverse_for_any_module_layout(ps: list[tuple[float, float]], t: Twist) -> None:
    kin = SwerveKinematics(ps)
    fk = kin.to_twist(kin.to_module_states(t))
    assert abs(fk.twist.vx - t.vx) < 1e-7 and abs(fk.twist.vy - t.vy) < 1e-7 and abs(fk.twist.wz - t.wz) < 1e-7


def test_inverse_kinematics_matches_design_equation() -> None:
    x, y = KIN.positions[0]
    states = KIN.to_module_states(Twist(0.1, -0.05, 0.3))
    ux, uy = 0.1 - 0.3 * y, -0.05 + 0.3 * x
    assert states[0].speed_mps == pytest.approx(math.hypot(ux, uy))
    assert states[0].angle_rad == pytest.approx(math.atan2(uy, ux))


def test_pure_sideways_and_turning_in_place() -> None:
    side = KIN.to_module_states(Twist(0.0, 0.2, 0.0))
    assert all(s.speed_mps == pytest.approx(0.2) and s.angle_rad == pytest.approx(math.pi / 2) for s in side)
    spin = KIN.to_module_states(Twist(0.0, 0.0, 0.5))
    # each wheel tangent to the circle through it: velocity perpendicular to its position vector
    for (x, y), s in zip(KIN.positions, spin):
        vx, vy = s.velocity
        assert vx * x + vy * y == pytest.approx(0.0, abs=1e-12)
        assert s.speed_mps == pytest.approx(0.5 * math.hypot(x, y))


def test_slip_residual_flags_a_non_rigid_measurement() -> None:
    states = list(KIN.to_module_states(Twist(0.2, 0.0, 0.0)))
    assert KIN.to_twist(states).residual_mps < 1e-12
    states[1] = ModuleState(0.1, 0.0)  # one wheel slips: the two wheels disagree along the line joining them
    assert KIN.to_twist(states).residual_mps > 0.02


def test_zero_speed_module_keeps_its_previous_angle() -> None:
    previous = (ModuleState(0.0, 1.2), ModuleState(0.0, -0.7))
    states = KIN.to_module_states(Twist(), previous)
    assert [s.angle_rad for s in states] == [1.2, -0.7]
    assert all(s.speed_mps == 0.0 for s in states)


def test_kinematics_rejects_degenerate_layouts() -> None:
    with pytest.raises(ValueError, match="at least 2"):
        SwerveKinematics([(0.0, 0.0)])
    with pytest.raises(ValueError, match="rotation"):
        SwerveKinematics([(0.5, 0.5), (0.5, 0.5)])


# --------------------------------------------------------------------------- optimisation


@given(speeds, angles, angles)
def test_optimize_keeps_the_velocity_vector_and_turns_at_most_90_degrees(v: float, a: float, cur: float) -> None:
    wide = SteeringLimits(-1e6, 1e6)
    out = optimize(ModuleState(v, a), cur, wide)
    ox, oy = out.velocity
    ix, iy = ModuleState(v, a).velocity
    assert abs(ox - ix) < 1e-9 and abs(oy - iy) < 1e-9
    assert abs(out.angle_rad - cur) <= math.pi / 2 + 1e-9


@given(speeds, angles, angles, st.floats(-math.pi, 0.0), st.floats(math.pi, 2 * math.pi))
def test_optimize_respects_steering_limits(v: float, a: float, cur: float, lo: float, hi_span: float) -> None:
    limits = SteeringLimits(lo, lo + hi_span)
    out = optimize(ModuleState(v, a), cur, limits)
    assert limits.min_rad - 1e-9 <= out.angle_rad <= limits.max_rad + 1e-9
    ox, oy = out.velocity
    ix, iy = ModuleState(v, a).velocity
    assert abs(ox - ix) < 1e-9 and abs(oy - iy) < 1e-9


def test_optimize_reverses_instead_of_turning_half_a_turn() -> None:
    out = optimize(ModuleState(0.3, math.pi), 0.0)
    assert out.speed_mps == pytest.approx(-0.3) and out.angle_rad == pytest.approx(0.0)
    with pytest.raises(ValueError, match="span"):
        SteeringLimits(-1.0, 1.0)


def test_cosine_scaling_and_desaturation() -> None:
    assert cosine_scale(ModuleState(0.4, 0.0), 0.0).speed_mps == pytest.approx(0.4)
    assert cosine_scale(ModuleState(0.4, 0.0), math.pi / 3).speed_mps == pytest.approx(0.2)
    assert cosine_scale(ModuleState(0.4, 0.0), 2.0).speed_mps == 0.0
    out = desaturate([ModuleState(1.0, 0.1), ModuleState(-0.5, 0.2)], 0.5)
    assert [s.speed_mps for s in out] == pytest.approx([0.5, -0.25])
    assert [s.angle_rad for s in out] == [0.1, 0.2]
    same = [ModuleState(0.2, 0.0), ModuleState(0.1, 0.0)]
    assert desaturate(same, 0.5) == tuple(same)


# --------------------------------------------------------------------------- limits


def test_twist_limits_clamp_and_accelerate() -> None:
    lim = ROBOT.twist_limits()
    assert lim.clamp(1.0, -1.0, 9.0) == (0.2, -0.2, 0.5)
    assert lim.clamp(-1.0, math.nan, math.inf) == (-0.1, 0.0, 0.0)
    t = lim.accelerate((0.0, 0.0, 0.0), (0.2, 0.2, 0.5), 0.1)
    assert t == pytest.approx((0.05, 0.05, 0.1))
    assert lim.accelerate(t, (0.2, 0.2, 0.5), 0.0) == t
    assert lim.accelerate(t, (0.2, 0.2, 0.5), math.nan) == t


@given(twists, twists, st.floats(1e-4, 0.05))
def test_acceleration_limit_never_exceeded(cur: Twist, target: Twist, dt: float) -> None:
    lim = TwistLimits()
    vx, vy, wz = lim.accelerate((cur.vx, cur.vy, cur.wz), (target.vx, target.vy, target.wz), dt)
    assert abs(vx - cur.vx) <= lim.ax_max_mps2 * dt + 1e-12
    assert abs(vy - cur.vy) <= lim.ay_max_mps2 * dt + 1e-12
    assert abs(wz - cur.wz) <= lim.alpha_max_radps2 * dt + 1e-12


# --------------------------------------------------------------------------- odometry


@settings(max_examples=60)
@given(twists, st.floats(-math.pi, math.pi), st.integers(1, 400))
def test_odometry_of_constant_twist_equals_closed_form_arc(t: Twist, theta0: float, steps: int) -> None:
    start = Pose(1.0, -2.0, theta0)
    dt = 0.01
    pose = start
    for _ in range(steps):
        pose = pose.integrate(t, dt)
    ref = arc_pose(start, t, steps * dt)
    assert abs(pose.x - ref.x) < 1e-9 and abs(pose.y - ref.y) < 1e-9
    assert abs(wrap_angle(pose.theta - ref.theta)) < 1e-9


def test_arc_closed_form_full_circle_and_euler_drift() -> None:
    t = Twist(0.2, 0.0, 0.5)
    full = arc_pose(Pose(), t, 2 * math.pi / 0.5)
    assert full.x == pytest.approx(0.0, abs=1e-12) and full.y == pytest.approx(0.0, abs=1e-12)
    exact = Pose().integrate(t, 2 * math.pi / 0.5)
    assert exact.x == pytest.approx(0.0, abs=1e-12) and exact.y == pytest.approx(0.0, abs=1e-12)


# --------------------------------------------------------------------------- motor units


def test_motor_units_follow_paper_equations() -> None:
    u = MotorUnits(wheel_radius_m=0.1, gear_ratio=20.0, steer_counts_per_rev=4000.0, steer_zero_counts=100)
    # eq. 7: v = V * 2 pi R / (J * 60)
    assert u.rpm_to_mps(1200.0) == pytest.approx(1200.0 * 2 * math.pi * 0.1 / (20.0 * 60.0))
    assert u.speed_command(u.rpm_to_mps(1200.0)) == 1200
    # eq. 8: theta = (P - P0) * 2 pi / N
    assert u.counts_to_rad(1100) == pytest.approx(1000 * 2 * math.pi / 4000.0)
    assert u.steer_command(math.pi / 2) == 1100
    assert u.speed_command(100.0) == 3000  # clamped to max_rpm
    with pytest.raises(ValueError, match="non-finite"):
        u.speed_command(math.nan)
    with pytest.raises(ValueError, match="non-finite"):
        u.steer_command(math.inf)
    with pytest.raises(ValueError, match="wheel_radius_m"):
        MotorUnits(wheel_radius_m=0.0)


@given(st.floats(-0.5, 0.5), st.floats(-6.0, 6.0))
def test_motor_unit_round_trips(v: float, theta: float) -> None:
    u = MotorUnits(traction_sign=-1, steer_sign=-1, steer_zero_counts=-1234)
    assert u.rpm_to_mps(u.mps_to_rpm(v)) == pytest.approx(v)
    assert u.counts_to_rad(u.rad_to_counts(theta)) == pytest.approx(theta)
    assert abs(u.counts_to_rad(u.steer_command(theta)) - theta) <= math.pi / u.steer_counts_per_rev + 1e-12


# --------------------------------------------------------------------------- wheel odometry and the controller


def _controller_parts():
    from services.drive.controller import DriveController, ModuleFeedback, WheelOdometry

    units = [MotorUnits(), MotorUnits()]
    return DriveController(KIN, units, ROBOT.twist_limits()), WheelOdometry(KIN, units), ModuleFeedback


def test_wheel_odometry_integrates_counts_across_wrap_and_rejects_jumps() -> None:
    _, odo, fb = _controller_parts()
    per_m = 1.0 / MotorUnits().m_per_count
    start = 2**31 - 1000
    odo.update([fb(start), fb(start)])
    wrapped = start + int(0.6 * per_m) - 2**32  # the S32 counter wrapped during a 0.6 m step
    odo.update([fb(wrapped), fb(wrapped)])
    assert odo.rejected_steps == 1 and odo.pose.x == 0.0  # 0.6 m in one step (> max_step_m) is a glitch
    c = wrapped + int(0.1 * per_m)
    odo.update([fb(c), fb(c)])
    assert odo.pose.x == pytest.approx(0.1, abs=1e-4) and odo.distance_m == pytest.approx(0.1, abs=1e-4)


def test_wheel_odometry_blends_the_imu_yaw_increment() -> None:
    _, odo, fb = _controller_parts()
    odo.update([fb(0), fb(0)])
    odo.update([fb(0), fb(0)], imu_dyaw_rad=0.1, imu_weight=0.5)  # wheels say no turn, the gyro says 0.1 rad
    assert odo.pose.theta == pytest.approx(0.05)
    odo.update([fb(0), fb(0)], imu_dyaw_rad=math.nan, imu_weight=1.0)  # a bad gyro value is ignored
    assert odo.pose.theta == pytest.approx(0.05)


def test_controller_ramps_holds_angles_and_refuses_non_finite() -> None:
    ctl, _, _ = _controller_parts()
    out = ctl.command(Twist(0.2, 0.0, 0.0), 0.1)
    assert out.twist.vx == pytest.approx(0.05)  # 0.5 m/s^2 for 0.1 s
    ctl.command(Twist(0.0, 0.2, 0.0), 1.0)
    ctl.command(Twist(0.0, 0.2, 0.0), 1.0)
    held = [m.angle_rad for m in ctl.setpoints]
    out = ctl.command(Twist(), 1.0)  # at rest: the wheels keep their angle, no snap back to 0
    assert [m.angle_rad for m in out.modules] == held and all(m.speed_mps == 0.0 for m in out.modules)
    # units whose rpm factor underflows to 0: the conversion fails inside the chain; the robot is stopped instead
    ctl.units = (MotorUnits(wheel_radius_m=5e-324, gear_ratio=1e10),) * 2
    out = ctl.command(Twist(0.1, 0.0, 0.0), 1.0)
    assert out.refused and all(m.traction_rpm == 0 for m in out.motors) and ctl.refusals == 1
