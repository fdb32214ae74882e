"""Exact SE(2) dead reckoning: integrate a body twist held constant over each step (docs/architecture.md, Kinematics).

For a body displacement (dx, dy, dtheta) over one step (twist * dt), the pose moves along the arc

    exp(dx, dy, dth) = ( dx*s - dy*c,  dx*c + dy*s,  dth ),   s = sin(dth)/dth,  c = (1 - cos(dth))/dth

expressed in the body frame at the start of the step, then rotated by the heading into the odom frame. Unlike
the paper's Euler step (eq. 6), it has no drift when translating while turning.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from services.common.se2 import compose, wrap_angle
from services.drive.kinematics import Twist


@dataclass(frozen=True, slots=True)
class Pose:
    """A planar pose: x, y in m, theta in rad (wrapped to (-pi, pi])."""

    x: float = 0.0
    y: float = 0.0
    theta: float = 0.0

    def exp(self, dx: float, dy: float, dtheta: float) -> Pose:
        """This pose moved by a body-frame displacement along a constant-twist arc."""
        if abs(dtheta) < 1e-9:
            s = 1.0 - dtheta * dtheta / 6.0
            c = 0.5 * dtheta
        else:
            half = 0.5 * dtheta
            s = math.sin(dtheta) / dtheta
            c = math.sin(half) * math.sin(half) * 2.0 / dtheta  # (1 - cos d)/d without cancellation
        bx = dx * s - dy * c
        by = dx * c + dy * s
        return Pose(*compose((self.x, self.y, self.theta), (bx, by, dtheta)))

    def integrate(self, twist: Twist, dt_s: float) -> Pose:
        """The pose after holding ``twist`` (body frame) for ``dt_s`` seconds."""
        return self.exp(twist.vx * dt_s, twist.vy * dt_s, twist.wz * dt_s)


def arc_pose(start: Pose, twist: Twist, t_s: float) -> Pose:
    """Closed form of a constant body twist held for ``t_s``: a circle of radius |v|/|wz| (or a line)."""
    # d/dt p = R(theta(t)) v  =>  p(t) - p0 = [ (sin th1 - sin th0) -(cos th1 - cos th0) ] applied to v, over w,
    # written with half-angle products so that a small w does not cancel: sin a - sin b = 2 cos(m) sin(h), ...
    th1 = start.theta + twist.wz * t_s
    h = 0.5 * twist.wz * t_s
    k = 0.5 * t_s * (math.sin(h) / h if abs(h) > 1e-12 else 1.0)  # = sin(h) / w
    m = start.theta + h
    ds, dc = 2.0 * math.cos(m) * k, -2.0 * math.sin(m) * k  # (sin th1 - sin th0)/w, (cos th1 - cos th0)/w
    x = start.x + twist.vx * ds + twist.vy * dc
    y = start.y - twist.vx * dc + twist.vy * ds
    return Pose(x, y, wrap_angle(th1))
