"""zagv messages to Foxglove schemas (``foxglove-sdk``), an I/O-free core.

- ``scan`` -> foxglove.LaserScan in the scan's frame (``laser``); its ``mount`` is the base_link -> laser transform.
- ``map``, ``nav/costmap`` -> foxglove.Grid with one ``uint8`` field ``occupancy`` (0..100, 255 unknown) whose pose
  is the map origin (cell (0, 0)'s corner); Foxglove colours it with its map palette.
- ``odom`` -> odom -> base_link, ``tf/map_odom`` -> map -> odom, scan mount -> base_link -> laser
  (foxglove.FrameTransforms, REP-105).
- ``nav/path``, ``nav/local_plan``, ``particles`` -> foxglove.PosesInFrame.
- footprint (chassis circle, ``RobotSpec.chassis_radius_m``) and swerve modules (a wheel box per module, turned by
  its measured steer angle from ``wheels``) -> foxglove.SceneUpdate in base_link.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from foxglove import messages as fm

from proto import codec
from proto import messages as m
from services.common.robot import RobotSpec
from services.common.se2 import quaternion_to_yaw, yaw_to_quaternion

WHEEL_LENGTH_M = 0.2
WHEEL_WIDTH_M = 0.08


def timestamp(stamp_s: float) -> fm.Timestamp:
    ns = max(0, int(round(stamp_s * 1e9))) if math.isfinite(stamp_s) else 0
    return fm.Timestamp(sec=ns // 1_000_000_000, nsec=ns % 1_000_000_000)


def quat(theta: float) -> fm.Quaternion:
    x, y, z, w = yaw_to_quaternion(theta)
    return fm.Quaternion(x=x, y=y, z=z, w=w)


def pose(x: float, y: float, theta: float) -> fm.Pose:
    return fm.Pose(position=fm.Vector3(x=float(x), y=float(y), z=0.0), orientation=quat(float(theta)))


def laser_scan(s: m.LaserScan) -> fm.LaserScan:
    ranges = codec.array(s, "ranges").astype(float)
    ranges[~np.isfinite(ranges)] = math.inf
    n = len(ranges)
    end = s.angle_min + s.angle_increment * (n - 1) if n else s.angle_max
    return fm.LaserScan(timestamp=timestamp(s.stamp), frame_id=s.frame, pose=pose(0.0, 0.0, 0.0),
                        start_angle=s.angle_min, end_angle=end, ranges=ranges.tolist(),
                        intensities=codec.array(s, "intensities").astype(float).tolist())


def grid(g: m.OccupancyGrid) -> fm.Grid:
    """Occupancy as uint8 cells: -1 (unknown) becomes 255."""
    cells = np.frombuffer(g.data, np.int8).astype(np.uint8).tobytes()
    field = fm.PackedElementField(name="occupancy", offset=0, type=fm.PackedElementFieldNumericType.Uint8)
    return fm.Grid(timestamp=timestamp(g.stamp), frame_id=g.frame, pose=pose(g.origin.x, g.origin.y, g.origin.theta),
                   column_count=g.width, cell_size=fm.Vector2(x=g.resolution, y=g.resolution), row_stride=g.width,
                   cell_stride=1, fields=[field], data=cells)


def transform(stamp_s: float, parent: str, child: str, x: float, y: float, theta: float) -> fm.FrameTransform:
    return fm.FrameTransform(timestamp=timestamp(stamp_s), parent_frame_id=parent, child_frame_id=child,
                             translation=fm.Vector3(x=float(x), y=float(y), z=0.0), rotation=quat(float(theta)))


def transforms(msg: m.Message) -> fm.FrameTransforms | None:
    """The transform a message carries (odom, tf/map_odom, a scan's mount); None for other messages."""
    if isinstance(msg, m.Odometry):
        p = msg.pose
        return fm.FrameTransforms(transforms=[transform(msg.stamp, msg.frame, msg.child_frame, p.x, p.y, p.theta)])
    if isinstance(msg, m.Transform2D):
        return fm.FrameTransforms(transforms=[transform(msg.stamp, msg.parent, msg.child, msg.x, msg.y, msg.theta)])
    if isinstance(msg, m.LaserScan):
        p = msg.mount
        return fm.FrameTransforms(transforms=[transform(msg.stamp, "base_link", msg.frame, p.x, p.y, p.theta)])
    return None


def poses(msg: m.Path | m.PoseArray) -> fm.PosesInFrame:
    rows = codec.array(msg, "poses")
    return fm.PosesInFrame(timestamp=timestamp(msg.stamp), frame_id=msg.frame,
                           poses=[pose(x, y, t) for x, y, t in rows.tolist()])


def robot_scene(robot: RobotSpec, wheels: m.WheelStates | None, stamp_s: float) -> fm.SceneUpdate:
    """Footprint circle and one box per swerve module (turned by its steer angle), in base_link."""
    n = 48
    circle = [fm.Point3(x=robot.chassis_radius_m * math.cos(2 * math.pi * k / n),
                        y=robot.chassis_radius_m * math.sin(2 * math.pi * k / n), z=0.0) for k in range(n + 1)]
    footprint = fm.SceneEntity(
        timestamp=timestamp(stamp_s), frame_id="base_link", id="footprint", frame_locked=True,
        lines=[fm.LinePrimitive(type=fm.LinePrimitiveLineType.LineStrip, pose=pose(0, 0, 0), thickness=0.02,
                                scale_invariant=False, points=circle, color=fm.Color(r=0.2, g=0.6, b=1.0, a=1.0))])
    steer = [mod.steer_rad for mod in wheels.modules] if wheels is not None else []
    cubes = []
    for i, geo in enumerate(robot.modules):
        angle = steer[i] if i < len(steer) and math.isfinite(steer[i]) else 0.0
        cubes.append(fm.CubePrimitive(pose=pose(geo.x_m, geo.y_m, angle),
                                      size=fm.Vector3(x=WHEEL_LENGTH_M, y=WHEEL_WIDTH_M, z=0.1),
                                      color=fm.Color(r=1.0, g=0.55, b=0.0, a=0.9)))
    modules = fm.SceneEntity(timestamp=timestamp(stamp_s), frame_id="base_link", id="modules", frame_locked=True,
                             cubes=cubes)
    return fm.SceneUpdate(entities=[footprint, modules])


def goal_from_json(doc: dict[str, Any]) -> tuple[float, float, float]:
    """(x, y, theta) of a published goal: geometry_msgs/PoseStamped or foxglove PoseInFrame as JSON, or a Pose."""
    body = doc.get("pose", doc)
    pos, ori = body["position"], body.get("orientation", {"x": 0, "y": 0, "z": 0, "w": 1})
    x, y = float(pos["x"]), float(pos["y"])
    qx, qy, qz, qw = (float(ori.get(k, 0.0)) for k in ("x", "y", "z", "w"))
    theta = quaternion_to_yaw(qx, qy, qz, qw)
    if not all(map(math.isfinite, (x, y, theta))):
        raise ValueError("goal pose is not finite")
    return x, y, theta
