"""Motor units of one swerve module (paper eq. 7 and 8).

- traction (eq. 7):  v = V * 2*pi*R / (J * 60)     v wheel speed m/s, V motor speed rpm, R wheel radius m,
                                                    J gear ratio (motor turns per wheel turn)
  and for odometry from encoder counts:  s = C * 2*pi*R / (J * C_rev)   with C_rev counts per motor turn.
- steering (eq. 8):  theta = (P - P0) * 2*pi / N   theta steering angle rad, P steering counts, P0 the count at
                                                    theta = 0, N counts per steering (module) revolution.

Commands are rounded to integers, clamped to the motor's range, and a non-finite input is refused (ValueError):
a NaN never becomes a motor command. The drive converts with these constants and the simulated RoboteQ motors use
the same ones, so both sides of the CAN bus agree by construction.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

S32_MIN, S32_MAX = -(2**31), 2**31 - 1


@dataclass(frozen=True, slots=True)
class MotorUnits:
    """Conversion constants of one module; ``*_sign`` is +1 or -1 for the motor's mounting direction."""

    wheel_radius_m: float = 0.1
    gear_ratio: float = 30.0
    traction_counts_per_rev: float = 4096.0
    steer_counts_per_rev: float = 4096.0 * 50.0
    steer_motor_counts_per_rev: float = 4096.0
    steer_zero_counts: int = 0
    max_rpm: float = 3000.0
    traction_sign: int = 1
    steer_sign: int = 1

    def __post_init__(self) -> None:
        for name in ("wheel_radius_m", "gear_ratio", "traction_counts_per_rev", "steer_counts_per_rev",
                     "steer_motor_counts_per_rev", "max_rpm"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"motor units: {name} must be a finite number > 0, got {value}")
        if self.traction_sign not in (1, -1) or self.steer_sign not in (1, -1):
            raise ValueError("motor units: traction_sign and steer_sign must be +1 or -1")

    # ------------------------------------------------------------------ traction (eq. 7)

    @property
    def mps_per_rpm(self) -> float:
        return 2.0 * math.pi * self.wheel_radius_m / (self.gear_ratio * 60.0)

    @property
    def m_per_count(self) -> float:
        return 2.0 * math.pi * self.wheel_radius_m / (self.gear_ratio * self.traction_counts_per_rev)

    def rpm_to_mps(self, rpm: float) -> float:
        return self.traction_sign * rpm * self.mps_per_rpm

    def mps_to_rpm(self, mps: float) -> float:
        return self.traction_sign * mps / self.mps_per_rpm

    def counts_to_m(self, counts: float) -> float:
        return self.traction_sign * counts * self.m_per_count

    def speed_command(self, mps: float) -> int:
        """Traction command in integer rpm, clamped to +-max_rpm; raises ValueError for a non-finite speed."""
        if not math.isfinite(mps):
            raise ValueError(f"non-finite wheel speed {mps!r} refused")
        limit = min(self.max_rpm, S32_MAX)
        return int(round(min(max(self.mps_to_rpm(mps), -limit), limit)))

    # ------------------------------------------------------------------ steering (eq. 8)

    def counts_to_rad(self, counts: float) -> float:
        return self.steer_sign * (counts - self.steer_zero_counts) * 2.0 * math.pi / self.steer_counts_per_rev

    def rad_to_counts(self, rad: float) -> float:
        return self.steer_zero_counts + self.steer_sign * rad * self.steer_counts_per_rev / (2.0 * math.pi)

    @property
    def steer_counts_per_motor_rpm_s(self) -> float:
        """Steering counts per second at 1 steering-motor rpm (``steer_motor_counts_per_rev`` / 60)."""
        return self.steer_motor_counts_per_rev / 60.0

    def steer_command(self, rad: float) -> int:
        """Steering command in integer counts (S32); raises ValueError for a non-finite angle."""
        if not math.isfinite(rad):
            raise ValueError(f"non-finite steering angle {rad!r} refused")
        return int(round(min(max(self.rad_to_counts(rad), S32_MIN), S32_MAX)))
