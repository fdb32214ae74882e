"""SE(2) on poses ``(x_m, y_m, theta_rad)``: the one angle wrap, composition, inverse and point transform.

Every function takes either plain tuples (one pose, exact ``math`` arithmetic, a tuple back) or numpy arrays of
shape (3,) or (N, 3) (vectorised, an array back); an array in either argument selects the array form.

- ``wrap_angle(a)`` folds an angle into (-pi, pi] (the range of ``atan2``).
- ``compose(a, b) = a ⊕ b``: pose b given in frame a, expressed in a's parent frame:
  ``(xa + cos(ta) xb - sin(ta) yb, ya + sin(ta) xb + cos(ta) yb, wrap(ta + tb))``.
- ``inverse(a) = ⊖a`` with ``a ⊕ ⊖a = 0``; ``between(a, b) = ⊖a ⊕ b`` (pose b seen from frame a).
- ``transform_points(pose, p) = R(theta) p + t`` for points (N, 2) given in frame ``pose``; ``rotate(a, x, y)``
  the rotation alone, for vectors and grids of any shape.
- ``yaw_to_quaternion``/``quaternion_to_yaw``: a planar heading as the rotation about z of ROS messages.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import overload

import numpy as np

Pose2 = tuple[float, float, float]
"""(x_m, y_m, theta_rad)."""


@overload
def wrap_angle(angle_rad: float) -> float: ...
@overload
def wrap_angle(angle_rad: np.ndarray) -> np.ndarray: ...
def wrap_angle(angle_rad: float | np.ndarray) -> float | np.ndarray:
    """Angle(s) folded into (-pi, pi]: ``pi - ((pi - a) mod 2 pi)``; a scalar in range comes back unchanged."""
    if isinstance(angle_rad, np.ndarray):
        return math.pi - (math.pi - angle_rad) % math.tau
    folded = math.remainder(angle_rad, math.tau)  # exact IEEE remainder, in [-pi, pi]
    return folded + math.tau if folded <= -math.pi else folded


@overload
def compose(a: Sequence[float], b: Sequence[float]) -> Pose2: ...
@overload
def compose(a: np.ndarray, b: np.ndarray | Sequence[float]) -> np.ndarray: ...
@overload
def compose(a: Sequence[float], b: np.ndarray) -> np.ndarray: ...
def compose(a: np.ndarray | Sequence[float], b: np.ndarray | Sequence[float]) -> np.ndarray | Pose2:
    """a ⊕ b: pose b given in frame a, returned in a's parent frame (module docstring)."""
    if not isinstance(a, np.ndarray) and not isinstance(b, np.ndarray):
        c, s = math.cos(a[2]), math.sin(a[2])
        return (a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], wrap_angle(a[2] + b[2]))
    pa = np.asarray(a, float)
    pb = np.asarray(b, float)
    c_arr, s_arr = np.cos(pa[..., 2]), np.sin(pa[..., 2])
    x = pa[..., 0] + c_arr * pb[..., 0] - s_arr * pb[..., 1]
    y = pa[..., 1] + s_arr * pb[..., 0] + c_arr * pb[..., 1]
    return np.stack([x, y, wrap_angle(np.asarray(pa[..., 2] + pb[..., 2]))], axis=-1)


@overload
def inverse(a: Sequence[float]) -> Pose2: ...
@overload
def inverse(a: np.ndarray) -> np.ndarray: ...
def inverse(a: np.ndarray | Sequence[float]) -> np.ndarray | Pose2:
    """⊖a = (-R(theta)^T t, -theta), so that a ⊕ ⊖a = 0."""
    if not isinstance(a, np.ndarray):
        c, s = math.cos(a[2]), math.sin(a[2])
        return (-c * a[0] - s * a[1], s * a[0] - c * a[1], wrap_angle(-a[2]))
    pa = np.asarray(a, float)
    c_arr, s_arr = np.cos(pa[..., 2]), np.sin(pa[..., 2])
    x = -c_arr * pa[..., 0] - s_arr * pa[..., 1]
    y = s_arr * pa[..., 0] - c_arr * pa[..., 1]
    return np.stack([x, y, wrap_angle(np.asarray(-pa[..., 2]))], axis=-1)


@overload
def between(a: Sequence[float], b: Sequence[float]) -> Pose2: ...
@overload
def between(a: np.ndarray, b: np.ndarray | Sequence[float]) -> np.ndarray: ...
@overload
def between(a: Sequence[float], b: np.ndarray) -> np.ndarray: ...
def between(a: np.ndarray | Sequence[float], b: np.ndarray | Sequence[float]) -> np.ndarray | Pose2:
    """(⊖a) ⊕ b: pose b seen from frame a."""
    if not isinstance(a, np.ndarray) and not isinstance(b, np.ndarray):
        return compose(inverse(a), b)
    return compose(inverse(np.asarray(a, float)), np.asarray(b, float))


@overload
def rotate(angle_rad: float, x: float, y: float) -> tuple[float, float]: ...
@overload
def rotate(angle_rad: float, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...
def rotate(angle_rad: float, x: float | np.ndarray, y: float | np.ndarray
           ) -> tuple[float, float] | tuple[np.ndarray, np.ndarray]:
    """R(angle) (x, y) = (cos a x - sin a y, sin a x + cos a y); ``rotate(-theta, ...)`` takes a vector of the
    parent frame into frame theta. x and y are floats or arrays of one shape (grids of points)."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return c * x - s * y, s * x + c * y  # type: ignore[return-value]


def transform_points(pose: np.ndarray | Sequence[float], points: np.ndarray) -> np.ndarray:
    """Points (N, 2) given in frame ``pose`` expressed in the parent frame: R(theta) p + t."""
    c, s = math.cos(float(pose[2])), math.sin(float(pose[2]))
    out = np.empty_like(points, dtype=float)
    out[:, 0] = c * points[:, 0] - s * points[:, 1] + pose[0]
    out[:, 1] = s * points[:, 0] + c * points[:, 1] + pose[1]
    return out


def yaw_to_quaternion(yaw_rad: float) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a rotation by ``yaw_rad`` about z: (0, 0, sin(yaw/2), cos(yaw/2))."""
    return 0.0, 0.0, math.sin(yaw_rad / 2.0), math.cos(yaw_rad / 2.0)


def quaternion_to_yaw(x: float, y: float, z: float, w: float) -> float:
    """The rotation about z of a quaternion (ROS's tf2 getYaw): atan2(2 (w z + x y), 1 - 2 (y² + z²))."""
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def interpolate(stamps_s: np.ndarray, poses: np.ndarray, at_s: np.ndarray | float) -> np.ndarray:
    """Poses (N, 3) linearly interpolated at ``at_s`` (angles along the shortest arc); clamped at the ends."""
    stamps = np.asarray(stamps_s, float)
    at = np.atleast_1d(np.asarray(at_s, float))
    unwrapped = np.unwrap(poses[:, 2])
    x = np.interp(at, stamps, poses[:, 0])
    y = np.interp(at, stamps, poses[:, 1])
    th = np.interp(at, stamps, unwrapped)
    return np.stack([x, y, wrap_angle(th)], axis=-1)


def interpolate_between(a: Pose2, b: Pose2, fraction: float) -> Pose2:
    """The pose ``fraction`` (0..1) of the way from ``a`` to ``b``: x and y linearly, the angle along the shorter
    arc (``interpolate`` for one stamp between two poses, without arrays)."""
    turn = wrap_angle(b[2] - a[2])
    return a[0] + fraction * (b[0] - a[0]), a[1] + fraction * (b[1] - a[1]), wrap_angle(a[2] + fraction * turn)


def robot_pose_and_frame(odom_pose: Pose2 | None, map_odom: Pose2 | None,
                         map_pose: Pose2 | None) -> tuple[Pose2, str] | None:
    """The robot's best known pose and its frame, as a viewer shows it: ``map_odom ∘ odom_pose`` in ``map`` when
    both are known; else the odometry pose in ``odom`` while no map pose exists; else the map pose itself."""
    if odom_pose is not None:
        if map_odom is not None:
            return compose(map_odom, odom_pose), "map"
        if map_pose is None:
            return odom_pose, "odom"
    if map_pose is not None:
        return map_pose, "map"
    return None
