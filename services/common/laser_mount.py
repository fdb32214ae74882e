"""Where a planar laser sits on the robot, from a chain of ROS transforms, and upside-down mounts.

A bag gives the laser's place as 3-D transforms (``/tf_static``: child -> parent, translation and quaternion),
often through intermediate frames (``laser -> laser_mount -> base_link``). ``planar_mount`` composes them up to the
robot's base frame and keeps what a 2-D scan needs: the laser origin (x, y) in the base plane, the heading of its
x axis, and whether its z axis points down (a scanner hung upside down, roll = π, as slam_toolbox and gmapping
detect it). Upside down, a beam at angle a in the laser frame lies at heading θ − a in the base frame instead of
θ + a: ``upright_scan`` re-expresses such a scan as the upright scan it equals (ranges reversed, first angle
−(a_min + (n − 1)·Δa), same increment), so everything downstream sees an ordinary, counter-clockwise scan.
A laser whose scan plane is tilted away from the base plane is refused: its returns are not a 2-D cut.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from services.common.se2 import yaw_to_quaternion

#: the scan plane may tilt this much from the base plane (a mount's roll or pitch) and still count as level
MAX_TILT_RAD = math.radians(10.0)


@dataclass(frozen=True)
class Transform3D:
    """A ROS transform: translation (m) and rotation (quaternion x, y, z, w) of a child frame in its parent."""

    translation_m: tuple[float, float, float]
    rotation_xyzw: tuple[float, float, float, float]

    @classmethod
    def planar(cls, x_m: float, y_m: float, theta_rad: float) -> Transform3D:
        return cls((x_m, y_m, 0.0), yaw_to_quaternion(theta_rad))

    @classmethod
    def from_ros(cls, transform: Any) -> Transform3D:
        """From a ``geometry_msgs/Transform`` (``translation`` x, y, z; ``rotation`` x, y, z, w)."""
        t, q = transform.translation, transform.rotation
        return cls((float(t.x), float(t.y), float(t.z)), (float(q.x), float(q.y), float(q.z), float(q.w)))


@dataclass(frozen=True)
class LaserMount:
    """The laser's origin (x_m, y_m) and x-axis heading (theta_rad) in the base frame; ``upside_down``: its z axis
    points down, so its beams sweep clockwise seen from above."""

    x_m: float = 0.0
    y_m: float = 0.0
    theta_rad: float = 0.0
    upside_down: bool = False

    @property
    def pose(self) -> np.ndarray:
        return np.array([self.x_m, self.y_m, self.theta_rad])


def planar_mount(laser_frame: str, transforms: Mapping[str, tuple[str, Transform3D]],
                 base_frame: str | None) -> LaserMount:
    """The mount of ``laser_frame`` in ``base_frame``: the transforms (child -> (parent, transform)) composed from
    the laser up to the base frame (or to the top of the chain when the base frame is not on it; no transform at
    all: the identity). ValueError when the laser's scan plane is tilted more than ``MAX_TILT_RAD`` from the base
    plane."""
    rotation = Rotation.identity()
    translation = np.zeros(3)
    frame = laser_frame
    seen: set[str] = set()
    while frame != base_frame and frame in transforms and frame not in seen:
        seen.add(frame)
        parent, step = transforms[frame]
        step_rotation = Rotation.from_quat(step.rotation_xyzw)
        translation = step_rotation.apply(translation) + np.asarray(step.translation_m, float)
        rotation = step_rotation * rotation
        frame = parent
    matrix = rotation.as_matrix()
    z_up = float(matrix[2, 2])  # the laser's z axis in the base frame, its vertical component
    tilt = math.acos(min(1.0, abs(z_up)))
    if tilt > MAX_TILT_RAD:
        raise ValueError(f"laser frame {laser_frame!r} is tilted {math.degrees(tilt):.1f} deg from the base plane "
                         f"of {base_frame or 'the top frame'!r} (at most {math.degrees(MAX_TILT_RAD):.0f} deg): "
                         f"not a planar scan")
    theta = math.atan2(float(matrix[1, 0]), float(matrix[0, 0]))  # heading of the laser's x axis
    return LaserMount(float(translation[0]), float(translation[1]), theta, upside_down=z_up < 0.0)


def upright_scan(angle_min_rad: float, angle_increment_rad: float, values: np.ndarray) -> tuple[float, np.ndarray]:
    """An upside-down scan as the upright scan it equals: beam i at laser angle a_i = a_min + i·Δa points along
    −a_i, so the reversed beams start at −(a_min + (n − 1)·Δa) and step by Δa. Returns (first angle, reversed
    ``values``); apply the same reversal to intensities."""
    values = np.asarray(values)
    n = len(values)
    return -(angle_min_rad + (n - 1) * angle_increment_rad), values[::-1].copy()
