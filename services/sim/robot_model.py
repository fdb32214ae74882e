"""Swerve robot physics: motors under closed-loop control, wheel kinematics, rigid-body motion on SE(2).

Pure, synchronous and I/O-free. Units (paper eq. 7 and 8, docs/architecture.md):

- traction: wheel rim speed ``v = rpm * 2*pi*R / (J * 60)`` (R wheel radius m, J gear ratio, rpm motor shaft);
  the traction encoder counts ``traction_cpr`` counts per motor revolution.
- steering: wheel angle ``theta = (P - P0) * 2*pi / N`` (P steering counts, P0 zero offset, N counts per steering
  revolution of the wheel). Steering motor rpm relates to the wheel rate by ``N / 60`` counts per second per rpm
  divided by the counts per motor revolution (``steer_cpr``).

The body twist is the least-squares fit of the modules' ground velocity vectors (what a rigid chassis does when
its wheels disagree: it scrubs), and the pose is integrated exactly for a constant twist over each step.
Everything here is scalar Python on purpose: two modules do not pay numpy's per-call overhead.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from services.common.motor_units import MotorUnits
from services.common.se2 import compose, wrap_angle


@dataclass
class TractionMotor:
    """Closed-loop speed: the setpoint ramps at accel/decel (rpm/s), the shaft follows it with lag ``tau_s``."""

    cpr: int
    target_rpm: float = 0.0
    ramped_rpm: float = 0.0
    speed_rpm: float = 0.0
    position_counts: float = 0.0
    accel_rpm_s: float = 2000.0
    decel_rpm_s: float = 2000.0
    tau_s: float = 0.02
    max_rpm: float = 3000.0
    amps: float = 0.0

    def step(self, dt: float) -> None:
        target = min(max(self.target_rpm, -self.max_rpm), self.max_rpm)
        r = self.ramped_rpm
        # accelerating when moving away from zero in the same direction, decelerating otherwise
        rate = self.accel_rpm_s if abs(target) > abs(r) and target * r >= 0.0 else self.decel_rpm_s
        dmax = rate * dt
        diff = target - r
        r = target if abs(diff) <= dmax else r + math.copysign(dmax, diff)
        self.ramped_rpm = r
        previous = self.speed_rpm
        alpha = dt / (self.tau_s + dt) if self.tau_s > 0.0 else 1.0
        self.speed_rpm = previous + alpha * (r - previous)
        self.position_counts += 0.5 * (previous + self.speed_rpm) * self.cpr / 60.0 * dt
        # a crude current model: friction when turning plus torque for acceleration (A)
        accel = (self.speed_rpm - previous) / dt if dt > 0.0 else 0.0
        self.amps = (1.5 if abs(self.speed_rpm) > 1.0 else 0.0) * math.copysign(1.0, self.speed_rpm) + 0.004 * accel


@dataclass
class SteerMotor:
    """Closed-loop count position with a trapezoidal profile: travel speed (rpm) and acceleration (rpm/s) limits."""

    cpr: int
    target_counts: float = 0.0
    position_counts: float = 0.0
    speed_counts_s: float = 0.0
    travel_rpm: float = 1500.0
    accel_rpm_s: float = 5000.0
    decel_rpm_s: float = 5000.0
    max_rpm: float = 3000.0
    amps: float = 0.0

    @property
    def speed_rpm(self) -> float:
        return self.speed_counts_s * 60.0 / self.cpr

    def hold(self) -> None:
        """Stop where the profile can stop (target = current position plus the braking distance)."""
        v = self.speed_counts_s
        dec = max(self.decel_rpm_s * self.cpr / 60.0, 1e-9)
        self.target_counts = self.position_counts + math.copysign(v * v / (2.0 * dec), v)

    def step(self, dt: float) -> None:
        to_cps = self.cpr / 60.0
        vmax = min(self.travel_rpm, self.max_rpm) * to_cps
        acc = self.accel_rpm_s * to_cps
        dec = self.decel_rpm_s * to_cps
        err = self.target_counts - self.position_counts
        v = self.speed_counts_s
        # the fastest speed toward the target from which we can still stop at it
        v_des = math.copysign(min(vmax, math.sqrt(2.0 * dec * abs(err))), err)
        dv = v_des - v
        rate = acc if abs(v_des) > abs(v) and v_des * v >= 0.0 else dec
        dmax = rate * dt
        v_new = v_des if abs(dv) <= dmax else v + math.copysign(dmax, dv)
        step = 0.5 * (v + v_new) * dt
        if abs(err) <= max(abs(step), 0.5) and abs(v_new) <= dmax + 1e-9:
            self.position_counts = self.target_counts  # arrived: settle exactly (the loop's deadband)
            v_new = 0.0
        else:
            self.position_counts += step
        accel = (v_new - v) / dt if dt > 0.0 else 0.0
        self.speed_counts_s = v_new
        self.amps = (0.8 if abs(v_new) > 1.0 else 0.0) + 0.00002 * abs(accel)


@dataclass
class SwerveModule:
    """One steering wheel at (x_m, y_m) in base_link: a traction motor and a steering motor."""

    x_m: float
    y_m: float
    units: MotorUnits
    traction: TractionMotor = field(init=False)
    steer: SteerMotor = field(init=False)

    def __post_init__(self) -> None:
        self.traction = TractionMotor(cpr=int(self.units.traction_counts_per_rev))
        self.steer = SteerMotor(cpr=int(self.units.steer_motor_counts_per_rev))
        self.steer.position_counts = self.steer.target_counts = float(self.units.steer_zero_counts)

    @property
    def steer_rad(self) -> float:
        return self.units.counts_to_rad(self.steer.position_counts)

    @property
    def rim_speed_mps(self) -> float:
        return self.units.rpm_to_mps(self.traction.speed_rpm)


def lsq_twist_matrix(modules: list[tuple[float, float]]) -> np.ndarray:
    """The 3 x 2n pseudo-inverse mapping stacked wheel velocities (vx_i, vy_i) to the body twist (vx, vy, wz).

    Rows of B per wheel: [1 0 -y_i; 0 1 x_i] (docs/architecture.md, Kinematics); twist = pinv(B) @ A.
    """
    b = np.zeros((2 * len(modules), 3))
    for i, (x, y) in enumerate(modules):
        b[2 * i] = (1.0, 0.0, -y)
        b[2 * i + 1] = (0.0, 1.0, x)
    return np.linalg.pinv(b)


def integrate_se2(x: float, y: float, th: float, vx: float, vy: float, wz: float, dt: float
                  ) -> tuple[float, float, float]:
    """Pose after moving with the constant body twist (vx, vy, wz) for dt (exact SE(2) exponential)."""
    dth = wz * dt
    if abs(dth) < 1e-9:
        s, c = 1.0 - dth * dth / 6.0, dth / 2.0  # sin(d)/d and (1 - cos d)/d
    else:
        s, c = math.sin(dth) / dth, (1.0 - math.cos(dth)) / dth
    dx = (s * vx - c * vy) * dt
    dy = (c * vx + s * vy) * dt
    return compose((x, y, th), (dx, dy, dth))


@dataclass
class SlipModel:
    """Ground speed = rim speed * (1 - slip_ratio + N(0, slip_noise)); seeded, noise drawn in batches."""

    slip_ratio: float = 0.0
    slip_noise: float = 0.0
    seed: int = 0
    _buf: np.ndarray = field(init=False, repr=False)
    _i: int = field(init=False, default=0, repr=False)

    def __post_init__(self) -> None:
        self._rng = np.random.default_rng(self.seed)
        self._refill()

    def _refill(self) -> None:
        self._buf = (1.0 - self.slip_ratio + self.slip_noise * self._rng.standard_normal(4096)).tolist()
        self._i = 0

    def factor(self) -> float:
        if self.slip_noise == 0.0:
            return 1.0 - self.slip_ratio
        if self._i >= len(self._buf):
            self._refill()
        f: float = self._buf[self._i]
        self._i += 1
        return f


class SwerveRobot:
    """The chassis: modules, true pose (world frame) and true body twist; ``step`` advances physics by dt.

    ``margin(x, y)`` (set by the simulation) is the footprint's clearance from the world at (x, y) in m (negative:
    overlapping). A step that would overlap more than now is refused: the body stops, and ``collided`` latches
    until ``teleport``.
    """

    def __init__(self, module_xy: list[tuple[float, float]], units: MotorUnits | list[MotorUnits],
                 slip: SlipModel | None = None) -> None:
        units_list = units if isinstance(units, list) else [units] * len(module_xy)
        if len(units_list) != len(module_xy):
            raise ValueError("one MotorUnits per module")
        self.modules = [SwerveModule(x, y, u) for (x, y), u in zip(module_xy, units_list)]
        p = lsq_twist_matrix(module_xy)
        self._p = [list(map(float, row)) for row in p]
        self.slip = slip or SlipModel()
        self.x = self.y = self.theta = 0.0
        self.vx = self.vy = self.wz = 0.0
        self.collided = False
        self.margin: Callable[[float, float], float] = lambda x, y: math.inf

    def teleport(self, x: float, y: float, theta: float) -> None:
        self.x, self.y, self.theta = x, y, wrap_angle(theta)
        self.vx = self.vy = self.wz = 0.0
        self.collided = False

    def wheel_ground_velocities(self) -> list[float]:
        """Stacked (vx_i, vy_i) ground velocities of the wheels in base_link (m/s), slip applied."""
        out: list[float] = []
        for m in self.modules:
            v = m.units.rpm_to_mps(m.traction.speed_rpm) * self.slip.factor()
            a = m.units.counts_to_rad(m.steer.position_counts)
            out.append(v * math.cos(a))
            out.append(v * math.sin(a))
        return out

    def step(self, dt: float) -> None:
        for m in self.modules:
            m.traction.step(dt)
            m.steer.step(dt)
        w = self.wheel_ground_velocities()
        p = self._p
        vx = sum(a * b for a, b in zip(p[0], w))
        vy = sum(a * b for a, b in zip(p[1], w))
        wz = sum(a * b for a, b in zip(p[2], w))
        x, y, th = integrate_se2(self.x, self.y, self.theta, vx, vy, wz, dt)
        if vx or vy:
            margin = self.margin(x, y)
            if margin < 0.0 and margin <= self.margin(self.x, self.y):
                # contact: the chassis does not move deeper into the obstacle (moving away stays possible)
                self.collided = True
                self.vx = self.vy = self.wz = 0.0
                return
        self.x, self.y, self.theta = x, y, th
        self.vx, self.vy, self.wz = vx, vy, wz
