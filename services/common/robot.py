"""The robot's shared facts: chassis geometry and the paper's Table 2 limits (docs/architecture.md, The robot)."""

from __future__ import annotations

import math

import msgspec


class ModuleGeometry(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """A swerve module's position (x_m, y_m) in base_link."""

    x_m: float
    y_m: float


def _default_modules() -> list[ModuleGeometry]:
    # Two drive wheels on one diagonal, each 0.63 m from the centre (the paper's chassis radius), at ±45°.
    r = 0.63 / math.sqrt(2.0)
    return [ModuleGeometry(r, r), ModuleGeometry(-r, -r)]


class RobotSpec(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """Geometry and velocity limits shared by drive, nav and sim ([robot] table)."""

    robot_id: str = "r1"
    chassis_radius_m: float = 0.63
    inflation_radius_m: float = 0.645
    mass_kg: float = 180.0
    modules: list[ModuleGeometry] = msgspec.field(default_factory=_default_modules)
    vx_min_mps: float = -0.1
    vx_max_mps: float = 0.2
    vy_max_mps: float = 0.2
    wz_max_radps: float = 0.5
    ax_max_mps2: float = 0.5
    ay_max_mps2: float = 0.5
    alpha_max_radps2: float = 1.0
    wheel_speed_max_mps: float = 0.5
    goal_xy_tolerance_m: float = 0.05
    goal_yaw_tolerance_rad: float = 0.05
    laser_mount_x_m: float = 0.45
    laser_mount_y_m: float = 0.0
    laser_mount_theta_rad: float = 0.0

    def clamp_twist(self, vx: float, vy: float, wz: float) -> tuple[float, float, float]:
        """Clamp a body twist (m/s, m/s, rad/s) to the Table 2 box; non-finite components become 0."""
        vx = vx if math.isfinite(vx) else 0.0
        vy = vy if math.isfinite(vy) else 0.0
        wz = wz if math.isfinite(wz) else 0.0
        return (
            min(max(vx, self.vx_min_mps), self.vx_max_mps),
            min(max(vy, -self.vy_max_mps), self.vy_max_mps),
            min(max(wz, -self.wz_max_radps), self.wz_max_radps),
        )
