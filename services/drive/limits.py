"""Velocity and acceleration limits of the commanded body twist (paper Table 2 box; RobotSpec accelerations)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from services.common.robot import RobotSpec
from services.drive.kinematics import Twist


@dataclass(frozen=True, slots=True)
class TwistLimits:
    """vx in [vx_min, vx_max] m/s, |vy| <= vy_max m/s, |wz| <= wz_max rad/s; |dvx/dt| <= ax m/s^2, etc."""

    vx_min_mps: float = -0.1
    vx_max_mps: float = 0.2
    vy_max_mps: float = 0.2
    wz_max_radps: float = 0.5
    ax_max_mps2: float = 0.5
    ay_max_mps2: float = 0.5
    alpha_max_radps2: float = 1.0

    @classmethod
    def from_robot(cls, robot: RobotSpec) -> TwistLimits:
        return cls(robot.vx_min_mps, robot.vx_max_mps, robot.vy_max_mps, robot.wz_max_radps,
                   robot.ax_max_mps2, robot.ay_max_mps2, robot.alpha_max_radps2)

    def clamp(self, t: Twist) -> Twist:
        """Clamp into the velocity box; a non-finite component becomes 0 (it never reaches a motor)."""
        vx = t.vx if math.isfinite(t.vx) else 0.0
        vy = t.vy if math.isfinite(t.vy) else 0.0
        wz = t.wz if math.isfinite(t.wz) else 0.0
        return Twist(min(max(vx, self.vx_min_mps), self.vx_max_mps),
                     min(max(vy, -self.vy_max_mps), self.vy_max_mps),
                     min(max(wz, -self.wz_max_radps), self.wz_max_radps))

    def accelerate(self, current: Twist, target: Twist, dt_s: float) -> Twist:
        """Move ``current`` toward ``target`` by at most a_max * dt per axis (dt <= 0 keeps ``current``)."""
        if not dt_s > 0.0 or not math.isfinite(dt_s):
            return current
        return Twist(_step(current.vx, target.vx, self.ax_max_mps2 * dt_s),
                     _step(current.vy, target.vy, self.ay_max_mps2 * dt_s),
                     _step(current.wz, target.wz, self.alpha_max_radps2 * dt_s))

    def stopping_time_s(self, t: Twist) -> float:
        """Time the acceleration limits need to bring ``t`` to rest (s)."""
        return max(abs(t.vx) / self.ax_max_mps2, abs(t.vy) / self.ay_max_mps2, abs(t.wz) / self.alpha_max_radps2)


def _step(value: float, target: float, max_delta: float) -> float:
    delta = target - value
    if delta > max_delta:
        return value + max_delta
    if delta < -max_delta:
        return value - max_delta
    return target
