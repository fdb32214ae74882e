"""The robot's shared facts: chassis geometry and the paper's Table 2 limits (docs/architecture.md, The robot)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import msgspec


class ModuleGeometry(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """A swerve module's position (x_m, y_m) in base_link."""

    x_m: float
    y_m: float


def _default_modules() -> list[ModuleGeometry]:
    # Two drive wheels on one diagonal, each 0.63 m from the centre (the paper's chassis radius), at ±45°.
    r = 0.63 / math.sqrt(2.0)
    return [ModuleGeometry(r, r), ModuleGeometry(-r, -r)]


Twist3 = tuple[float, float, float]
"""A body twist (vx m/s, vy m/s, wz rad/s)."""


@dataclass(frozen=True, slots=True)
class TwistLimits:
    """The commanded body twist's limits: vx in [vx_min, vx_max] m/s, |vy| <= vy_max m/s, |wz| <= wz_max rad/s,
    and per axis |dv/dt| <= ax, ay m/s^2, |dwz/dt| <= alpha rad/s^2 (the paper's Table 2; RobotSpec)."""

    vx_min_mps: float = -0.1
    vx_max_mps: float = 0.2
    vy_max_mps: float = 0.2
    wz_max_radps: float = 0.5
    ax_max_mps2: float = 0.5
    ay_max_mps2: float = 0.5
    alpha_max_radps2: float = 1.0

    def clamp(self, vx: float, vy: float, wz: float) -> Twist3:
        """Clamp into the velocity box; a non-finite component becomes 0 (it never reaches a motor)."""
        vx = vx if math.isfinite(vx) else 0.0
        vy = vy if math.isfinite(vy) else 0.0
        wz = wz if math.isfinite(wz) else 0.0
        return (min(max(vx, self.vx_min_mps), self.vx_max_mps),
                min(max(vy, -self.vy_max_mps), self.vy_max_mps),
                min(max(wz, -self.wz_max_radps), self.wz_max_radps))

    def accelerate(self, current: Twist3, target: Twist3, dt_s: float) -> Twist3:
        """Move ``current`` toward ``target`` by at most a_max * dt per axis (dt <= 0 or not finite keeps
        ``current``)."""
        if not dt_s > 0.0 or not math.isfinite(dt_s):
            return current
        return (_step(current[0], target[0], self.ax_max_mps2 * dt_s),
                _step(current[1], target[1], self.ay_max_mps2 * dt_s),
                _step(current[2], target[2], self.alpha_max_radps2 * dt_s))


TABLE2 = TwistLimits()
"""The paper's Table 2 limits: the defaults of every RobotSpec."""


class RobotSpec(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """Geometry and velocity limits shared by drive, nav and sim ([robot] table)."""

    robot_id: str = "r1"
    chassis_radius_m: float = 0.63
    inflation_radius_m: float = 0.645
    mass_kg: float = 180.0
    modules: list[ModuleGeometry] = msgspec.field(default_factory=_default_modules)
    vx_min_mps: float = TABLE2.vx_min_mps
    vx_max_mps: float = TABLE2.vx_max_mps
    vy_max_mps: float = TABLE2.vy_max_mps
    wz_max_radps: float = TABLE2.wz_max_radps
    ax_max_mps2: float = TABLE2.ax_max_mps2
    ay_max_mps2: float = TABLE2.ay_max_mps2
    alpha_max_radps2: float = TABLE2.alpha_max_radps2
    wheel_speed_max_mps: float = 0.5
    goal_xy_tolerance_m: float = 0.05
    goal_yaw_tolerance_rad: float = 0.05
    laser_mount_x_m: float = 0.45
    laser_mount_y_m: float = 0.0
    laser_mount_theta_rad: float = 0.0

    def twist_limits(self) -> TwistLimits:
        """The Table 2 velocity box and the acceleration limits as one TwistLimits."""
        return TwistLimits(self.vx_min_mps, self.vx_max_mps, self.vy_max_mps, self.wz_max_radps,
                           self.ax_max_mps2, self.ay_max_mps2, self.alpha_max_radps2)


def _step(value: float, target: float, max_delta: float) -> float:
    """``target``, or ``value`` moved by ``max_delta`` toward it when it is further."""
    delta = target - value
    if delta > max_delta:
        return value + max_delta
    if delta < -max_delta:
        return value - max_delta
    return target
