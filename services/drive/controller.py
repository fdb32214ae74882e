"""The drive's control law and odometry, I/O-free: twist in, motor commands out; encoder feedback in, pose out.

Command path (one call per control cycle):
    target twist -> velocity box (non-finite -> 0) -> acceleration limits -> inverse kinematics
    -> desaturation to the wheel-speed limit -> per module: hold the angle when stopped, optimise within the
    steering limits -> cosine scaling by the measured steering error -> motor units (rpm, counts).
Feedback path:
    traction encoder count deltas + steering counts -> wheel displacement vectors -> least-squares FK
    -> exact SE(2) step (optionally with the IMU's yaw increment blended in); speeds (rpm) -> FK -> body twist and
    the slip residual.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from services.common.motor_units import MotorUnits
from services.common.robot import TwistLimits
from services.drive.kinematics import (
    ZERO_TWIST,
    ModuleState,
    SteeringLimits,
    SwerveKinematics,
    Twist,
    cosine_scale,
    desaturate,
    optimize,
)
from services.drive.odometry import Pose

DEFAULT_STEERING = SteeringLimits()
ORIGIN = Pose()


@dataclass(frozen=True, slots=True)
class ModuleFeedback:
    """What one RoboteQ reports (ch1 traction, ch2 steering): counts, rpm, amps, FF/FS flags, per-motor FM flags."""

    traction_counts: int = 0
    steer_counts: int = 0
    traction_rpm: int = 0
    steer_rpm: int = 0
    traction_amps: float = 0.0
    steer_amps: float = 0.0
    fault_flags: int = 0
    status_flags: int = 0
    traction_motor_flags: int = 0
    steer_motor_flags: int = 0
    battery_v: float = 0.0


@dataclass(frozen=True, slots=True)
class MotorCommand:
    """One controller's setpoints: traction speed (rpm, ch1) and steering position (counts, ch2)."""

    traction_rpm: int
    steer_counts: int


@dataclass(frozen=True, slots=True)
class CommandResult:
    """A cycle's output: the limited body twist, the module setpoints (m/s, rad) and the motor commands."""

    twist: Twist
    modules: tuple[ModuleState, ...]
    motors: tuple[MotorCommand, ...]
    refused: bool = False  # a non-finite value was caught before the motors; the robot was stopped instead


@dataclass(frozen=True, slots=True)
class OdometryStep:
    """Odometry after one feedback update: pose (odom frame), measured body twist, slip residual (m/s)."""

    pose: Pose
    twist: Twist
    residual_mps: float


class DriveController:
    """Turns body twists into motor commands (stateful: the limited twist and the last module angles)."""

    def __init__(self, kinematics: SwerveKinematics, units: Sequence[MotorUnits], limits: TwistLimits,
                 steering: SteeringLimits = DEFAULT_STEERING, *, wheel_speed_max_mps: float = 0.5,
                 hold_speed_mps: float = 1e-4, cosine_scaling: bool = True) -> None:
        if len(units) != kinematics.module_count:
            raise ValueError(f"{kinematics.module_count} modules but {len(units)} motor unit sets")
        if not wheel_speed_max_mps > 0:
            raise ValueError(f"wheel_speed_max_mps must be > 0, got {wheel_speed_max_mps}")
        self.kinematics = kinematics
        self.units = tuple(units)
        self.limits = limits
        self.steering = steering
        self.wheel_speed_max_mps = wheel_speed_max_mps
        self.hold_speed_mps = hold_speed_mps
        self.cosine_scaling = cosine_scaling
        self.commanded: Twist = ZERO_TWIST
        self.setpoints: tuple[ModuleState, ...] = tuple(ModuleState() for _ in units)
        self.refusals = 0

    def reset(self, measured_angles: Sequence[float] | None = None) -> None:
        """Forget the motion (commanded twist 0); hold the modules at ``measured_angles`` when given."""
        self.commanded = ZERO_TWIST
        if measured_angles is not None:
            self.setpoints = tuple(ModuleState(0.0, a) for a in measured_angles)
        else:
            self.setpoints = tuple(ModuleState(0.0, s.angle_rad) for s in self.setpoints)

    def command(self, target: Twist, dt_s: float, measured_angles: Sequence[float] | None = None) -> CommandResult:
        """One cycle of the command path toward ``target`` (body twist) after ``dt_s`` seconds."""
        clamped = self.limits.clamp(target.vx, target.vy, target.wz)
        now = self.commanded
        commanded = Twist(*self.limits.accelerate((now.vx, now.vy, now.wz), clamped, dt_s))
        if not commanded.is_finite():
            commanded = ZERO_TWIST
        raw = desaturate(self.kinematics.to_module_states(commanded, self.setpoints, self.hold_speed_mps),
                         self.wheel_speed_max_mps)
        setpoints = []
        outputs = []
        for i, state in enumerate(raw):
            previous = self.setpoints[i].angle_rad
            if state.speed_mps == 0.0:
                opt = ModuleState(0.0, previous)
            else:
                opt = optimize(state, previous, self.steering)
            setpoints.append(opt)
            out = opt
            if self.cosine_scaling and measured_angles is not None:
                out = cosine_scale(opt, measured_angles[i])
            outputs.append(out)
        try:
            motors = tuple(MotorCommand(u.speed_command(o.speed_mps), u.steer_command(o.angle_rad))
                           for u, o in zip(self.units, outputs))
        except (ValueError, ArithmeticError):  # non-finite or unrepresentable: never sent to a motor
            return self._refuse()
        self.commanded = commanded
        self.setpoints = tuple(setpoints)
        return CommandResult(commanded, tuple(outputs), motors)

    def stop(self) -> CommandResult:
        """Zero wheel speed at once, modules held at their last angles (fault, disable, e-stop)."""
        self.commanded = ZERO_TWIST
        held = tuple(ModuleState(0.0, s.angle_rad) for s in self.setpoints)
        self.setpoints = held
        motors = tuple(MotorCommand(0, u.steer_command(s.angle_rad)) for u, s in zip(self.units, held))
        return CommandResult(ZERO_TWIST, held, motors)

    def _refuse(self) -> CommandResult:
        self.refusals += 1
        stopped = self.stop()
        return CommandResult(stopped.twist, stopped.modules, stopped.motors, refused=True)


def _counts_delta(new: int, old: int) -> int:
    """Difference of two S32 counter readings, across a wrap-around."""
    return ((new - old + 2**31) % 2**32) - 2**31


class WheelOdometry:
    """Dead reckoning from the controllers' encoder counts (exact SE(2) steps; survives link drops)."""

    def __init__(self, kinematics: SwerveKinematics, units: Sequence[MotorUnits], *, max_step_m: float = 0.5,
                 pose: Pose = ORIGIN) -> None:
        self.kinematics = kinematics
        self.units = tuple(units)
        self.max_step_m = max_step_m
        self.pose = pose
        self.twist = ZERO_TWIST
        self.residual_mps = 0.0
        self.distance_m = 0.0
        self.rejected_steps = 0
        self._last: tuple[tuple[int, float], ...] | None = None

    def rebaseline(self) -> None:
        """The next feedback starts a new count baseline (after a reconnect the counters may have restarted)."""
        self._last = None

    def update(self, feedback: Sequence[ModuleFeedback], imu_dyaw_rad: float | None = None,
               imu_weight: float = 0.0) -> OdometryStep:
        """Advance by the counts since the previous call; ``imu_dyaw_rad`` blends a gyro yaw increment in."""
        now = tuple((f.traction_counts, u.counts_to_rad(f.steer_counts)) for f, u in zip(feedback, self.units))
        speeds = [ModuleState(u.rpm_to_mps(f.traction_rpm), a) for f, u, (_, a) in zip(feedback, self.units, now)]
        fk = self.kinematics.to_twist(speeds)
        self.twist, self.residual_mps = fk.twist, fk.residual_mps
        last, self._last = self._last, now
        if last is not None:
            vectors = []
            for (c1, a1), (c0, a0), u in zip(now, last, self.units):
                d = u.counts_to_m(_counts_delta(c1, c0))
                a = 0.5 * (a0 + a1)
                vectors.append((d * math.cos(a), d * math.sin(a)))
            if max(math.hypot(*v) for v in vectors) > self.max_step_m:
                self.rejected_steps += 1  # a counter reset or a glitch, not motion: start a new baseline
            else:
                step = self.kinematics.to_twist_from_vectors(vectors).twist
                dyaw = step.wz
                if imu_dyaw_rad is not None and math.isfinite(imu_dyaw_rad) and imu_weight > 0.0:
                    dyaw = (1.0 - imu_weight) * dyaw + imu_weight * imu_dyaw_rad
                self.pose = self.pose.exp(step.vx, step.vy, dyaw)
                self.distance_m += math.hypot(step.vx, step.vy)
        return OdometryStep(self.pose, self.twist, self.residual_mps)
