"""zagv messages to and from standard ROS 2 messages (``rosbags`` typestore objects), an I/O-free core.

Mapping (topic name after ``agv/<id>/`` -> bag topic ``/<name>``):

- ``scan`` -> sensor_msgs/msg/LaserScan, and its ``mount`` (the laser's pose in base_link) as a base_link -> laser
  transform on ``/tf_static`` whenever it changes;
- ``odom`` -> nav_msgs/msg/Odometry, plus odom -> base_link on ``/tf``; ``tf/map_odom`` -> map -> odom on ``/tf``
  (REP-105: map -> odom -> base_link -> laser);
- ``map``, ``nav/costmap`` -> nav_msgs/msg/OccupancyGrid; ``nav/path``, ``nav/local_plan`` -> nav_msgs/msg/Path;
  ``cmd_vel`` -> geometry_msgs/msg/Twist; ``pose`` -> geometry_msgs/msg/PoseWithCovarianceStamped;
  ``particles`` -> geometry_msgs/msg/PoseArray; ``imu`` -> sensor_msgs/msg/Imu; ``clock`` ->
  rosgraph_msgs/msg/Clock;
- every other zagv message (``wheels``, ``nav/status``, ``sim/ground_truth``, ...) -> ``zagv_msgs/msg/Message``:
  the proto type name, the message as JSON (readable in any viewer) and its exact msgpack bytes (lossless).

From a ROS bag, a LaserScan's ``mount`` is composed along the fixed transforms up to base_link, and a scanner
hung upside down (roll π) has its scan re-expressed upright (``services/common/laser_mount.py``).

Planar poses become quaternions about z: q = (0, 0, sin θ/2, cos θ/2); θ = atan2(2(wz + xy), 1 − 2(y² + z²)).
3x3 covariances over (x, y, θ) sit at rows/columns (0, 1, 5) of the 6x6 ROS covariance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import msgspec
import numpy as np
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from proto import codec
from proto import messages as m
from proto.registry import TOPICS
from services.common.laser_mount import LaserMount, Transform3D, planar_mount, upright_scan
from services.common.se2 import quaternion_to_yaw, yaw_to_quaternion

#: the lossless carrier of zagv-only messages
ZAGV_MESSAGE_TYPE = "zagv_msgs/msg/Message"
ZAGV_MESSAGE_DEF = """\
std_msgs/Header header
# proto message type name (its JSON Schema is proto/schema/<type_name>.json)
string type_name
# the message as JSON (msgspec encoding; bytes fields base64)
string json
# the exact msgpack payload that travelled on Zenoh
uint8[] msgpack
"""

#: zagv topic -> standard ROS 2 type (topics not listed travel as ZAGV_MESSAGE_TYPE)
STANDARD_TYPES: dict[str, str] = {
    "scan": "sensor_msgs/msg/LaserScan",
    "odom": "nav_msgs/msg/Odometry",
    "map": "nav_msgs/msg/OccupancyGrid",
    "nav/costmap": "nav_msgs/msg/OccupancyGrid",
    "nav/path": "nav_msgs/msg/Path",
    "nav/local_plan": "nav_msgs/msg/Path",
    "cmd_vel": "geometry_msgs/msg/Twist",
    "pose": "geometry_msgs/msg/PoseWithCovarianceStamped",
    "particles": "geometry_msgs/msg/PoseArray",
    "imu": "sensor_msgs/msg/Imu",
    "clock": "rosgraph_msgs/msg/Clock",
    "tf/map_odom": "tf2_msgs/msg/TFMessage",
}
TF_TYPE = "tf2_msgs/msg/TFMessage"
COV_INDEX = (0, 1, 5)


def make_typestore() -> Typestore:
    """ROS 2 Humble's types plus ``zagv_msgs/msg/Message``."""
    store = get_typestore(Stores.ROS2_HUMBLE)
    store.register(get_types_from_msg(ZAGV_MESSAGE_DEF, ZAGV_MESSAGE_TYPE))
    return store


def bag_topic(name: str) -> str:
    """Bag topic of a zagv topic name: ``tf/map_odom`` -> ``/tf``, else ``/<name>``."""
    return "/tf" if name == "tf/map_odom" else f"/{name}"


def ros_type(name: str) -> str:
    return STANDARD_TYPES.get(name, ZAGV_MESSAGE_TYPE)


def stamp_to_ns(stamp_s: float) -> int:
    return int(round(stamp_s * 1e9))


def _cov6(cov3: list[float]) -> np.ndarray:
    out = np.zeros(36)
    if len(cov3) == 9:
        for i, a in enumerate(COV_INDEX):
            for j, b in enumerate(COV_INDEX):
                out[a * 6 + b] = cov3[i * 3 + j]
    return out


def _cov3(cov6: np.ndarray) -> list[float]:
    c = np.asarray(cov6, float)
    if c.size != 36:
        return [0.0] * 9
    return [float(c[a * 6 + b]) for a in COV_INDEX for b in COV_INDEX]


class RosEncoder:
    """zagv message -> ``(bag_topic, ros_type, ros_message)`` items (an odom also yields its /tf, a scan its
    /tf_static when the mount changes)."""

    def __init__(self, store: Typestore) -> None:
        self.store = store
        self.t = store.types
        self._mount: tuple[float, float, float] | None = None

    # --------------------------------------------------------------- building blocks
    def time(self, stamp_s: float) -> Any:
        ns = stamp_to_ns(stamp_s) if math.isfinite(stamp_s) else 0
        sec, nanosec = divmod(max(ns, 0), 1_000_000_000)
        return self.t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)

    def header(self, stamp_s: float, frame: str) -> Any:
        return self.t["std_msgs/msg/Header"](stamp=self.time(stamp_s), frame_id=frame)

    def quat(self, theta: float) -> Any:
        x, y, z, w = yaw_to_quaternion(theta)
        return self.t["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w)

    def pose(self, x: float, y: float, theta: float) -> Any:
        point = self.t["geometry_msgs/msg/Point"](x=float(x), y=float(y), z=0.0)
        return self.t["geometry_msgs/msg/Pose"](position=point, orientation=self.quat(float(theta)))

    def transform(self, stamp_s: float, parent: str, child: str, x: float, y: float, theta: float) -> Any:
        t = self.t
        tr = t["geometry_msgs/msg/Transform"](
            translation=t["geometry_msgs/msg/Vector3"](x=float(x), y=float(y), z=0.0), rotation=self.quat(theta))
        return t["geometry_msgs/msg/TransformStamped"](header=self.header(stamp_s, parent), child_frame_id=child,
                                                       transform=tr)

    def tf(self, *transforms: Any) -> Any:
        return self.t[TF_TYPE](transforms=list(transforms))

    def vector3(self, x: float, y: float, z: float) -> Any:
        return self.t["geometry_msgs/msg/Vector3"](x=float(x), y=float(y), z=float(z))

    def zagv(self, msg: m.Message) -> Any:
        """The lossless carrier: type name, JSON and the exact msgpack payload."""
        return self.t[ZAGV_MESSAGE_TYPE](
            header=self.header(float(getattr(msg, "stamp", 0.0) or 0.0), ""), type_name=type(msg).__name__,
            json=msgspec.json.encode(msg).decode(), msgpack=np.frombuffer(codec.encode(msg), np.uint8))

    # --------------------------------------------------------------- messages
    def encode(self, name: str, msg: m.Message) -> list[tuple[str, str, Any]]:
        t = self.t
        kind = STANDARD_TYPES.get(name)
        topic = bag_topic(name)
        out: list[tuple[str, str, Any]] = []
        if kind is None:
            return [(topic, ZAGV_MESSAGE_TYPE, self.zagv(msg))]
        if isinstance(msg, m.LaserScan):
            mount = (msg.mount.x, msg.mount.y, msg.mount.theta)
            if mount != self._mount:
                self._mount = mount
                out.append(("/tf_static", TF_TYPE,
                            self.tf(self.transform(msg.stamp, "base_link", msg.frame or "laser", *mount))))
            body = t[kind](header=self.header(msg.stamp, msg.frame), angle_min=msg.angle_min,
                           angle_max=msg.angle_max, angle_increment=msg.angle_increment,
                           time_increment=msg.time_increment, scan_time=msg.scan_time, range_min=msg.range_min,
                           range_max=msg.range_max, ranges=np.frombuffer(msg.ranges, "<f4").astype(np.float32),
                           intensities=np.frombuffer(msg.intensities, "<f4").astype(np.float32))
        elif isinstance(msg, m.Odometry):
            p, v = msg.pose, msg.twist
            twist = t["geometry_msgs/msg/Twist"](linear=self.vector3(v.vx, v.vy, 0.0),
                                                 angular=self.vector3(0.0, 0.0, v.wz))
            body = t[kind](
                header=self.header(msg.stamp, msg.frame), child_frame_id=msg.child_frame,
                pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=self.pose(p.x, p.y, p.theta),
                                                               covariance=_cov6(msg.pose_covariance)),
                twist=t["geometry_msgs/msg/TwistWithCovariance"](twist=twist,
                                                                 covariance=_cov6(msg.twist_covariance)))
            out.append((topic, kind, body))
            out.append(("/tf", TF_TYPE, self.tf(self.transform(msg.stamp, msg.frame, msg.child_frame,
                                                               p.x, p.y, p.theta))))
            return out
        elif isinstance(msg, m.Transform2D):
            body = self.tf(self.transform(msg.stamp, msg.parent, msg.child, msg.x, msg.y, msg.theta))
        elif isinstance(msg, m.OccupancyGrid):
            o = msg.origin
            info = t["nav_msgs/msg/MapMetaData"](map_load_time=self.time(msg.stamp), resolution=msg.resolution,
                                                 width=msg.width, height=msg.height,
                                                 origin=self.pose(o.x, o.y, o.theta))
            body = t[kind](header=self.header(msg.stamp, msg.frame), info=info,
                           data=np.frombuffer(msg.data, np.int8).copy())
        elif isinstance(msg, m.Path):
            rows = codec.array(msg, "poses")
            poses = [t["geometry_msgs/msg/PoseStamped"](header=self.header(msg.stamp, msg.frame),
                                                        pose=self.pose(*row)) for row in rows]
            body = t[kind](header=self.header(msg.stamp, msg.frame), poses=poses)
        elif isinstance(msg, m.Twist2D):
            body = t[kind](linear=self.vector3(msg.vx, msg.vy, 0.0), angular=self.vector3(0.0, 0.0, msg.wz))
        elif isinstance(msg, m.PoseWithCovariance):
            p = msg.pose
            body = t[kind](header=self.header(msg.stamp, msg.frame),
                           pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=self.pose(p.x, p.y, p.theta),
                                                                          covariance=_cov6(msg.covariance)))
        elif isinstance(msg, m.PoseArray):
            rows = codec.array(msg, "poses")
            body = t[kind](header=self.header(msg.stamp, msg.frame), poses=[self.pose(*row) for row in rows])
        elif isinstance(msg, m.Imu):
            cy, sy = math.cos(msg.yaw / 2), math.sin(msg.yaw / 2)
            cp, sp = math.cos(msg.pitch / 2), math.sin(msg.pitch / 2)
            cr, sr = math.cos(msg.roll / 2), math.sin(msg.roll / 2)
            q = t["geometry_msgs/msg/Quaternion"](x=sr * cp * cy - cr * sp * sy, y=cr * sp * cy + sr * cp * sy,
                                                  z=cr * cp * sy - sr * sp * cy, w=cr * cp * cy + sr * sp * sy)
            body = t[kind](header=self.header(msg.stamp, msg.frame), orientation=q,
                           orientation_covariance=np.zeros(9), angular_velocity=self.vector3(*msg.angular_velocity),
                           angular_velocity_covariance=np.zeros(9),
                           linear_acceleration=self.vector3(*msg.linear_acceleration),
                           linear_acceleration_covariance=np.zeros(9))
        elif isinstance(msg, m.Clock):
            body = t[kind](clock=self.time(msg.stamp))
        else:  # a registry change this module does not know yet: keep it losslessly
            return [(topic, ZAGV_MESSAGE_TYPE, self.zagv(msg))]
        out.append((topic, kind, body))
        return out


def _time_s(t: Any) -> float:
    return float(t.sec) + float(t.nanosec) * 1e-9


def _frame(frame_id: str) -> str:
    return frame_id.lstrip("/")


class UnsupportedMessage(ValueError):
    """A bag message zagv has no counterpart for (the replay reports it per topic and skips it)."""


@dataclass
class RosDecoder:
    """ROS message -> ``(zagv topic name, message)`` items. Keeps the laser mount from ``/tf_static`` (or ``/tf``)
    so that a replayed LaserScan carries it, as the live lidar service does."""

    #: child frame -> (parent, transform) of every fixed transform seen (``/tf_static``, and ``/tf`` outside the
    #: odom and map frames): the laser mount is composed along them up to ``base_link``
    transforms: dict[str, tuple[str, Transform3D]] = field(default_factory=dict)
    #: laser frame -> its mount, composed once per frame until a transform changes (not for every scan)
    mounts: dict[str, LaserMount] = field(default_factory=dict)

    def decode(self, topic: str, msgtype: str, msg: Any) -> list[tuple[str, m.Message]]:
        name = topic.lstrip("/")
        if msgtype == ZAGV_MESSAGE_TYPE:
            t = _proto_type(msg.type_name)
            return [(name, codec.decode_as(t, bytes(np.asarray(msg.msgpack, np.uint8)), topic))]
        if msgtype == "sensor_msgs/msg/LaserScan":
            frame = _frame(msg.header.frame_id)
            mount = self.mounts.get(frame)
            if mount is None:
                mount = self.mounts[frame] = planar_mount(frame, self.transforms, "base_link")
            angle_min, angle_max = float(msg.angle_min), float(msg.angle_max)
            ranges, intensities = np.asarray(msg.ranges, "<f4"), np.asarray(msg.intensities, "<f4")
            if mount.upside_down:  # re-expressed as the upright scan it equals (services/common/laser_mount.py)
                increment = float(msg.angle_increment)
                angle_min, ranges = upright_scan(angle_min, increment, ranges)
                angle_max = angle_min + (len(ranges) - 1) * increment
                intensities = intensities[::-1].copy()
            return [(name, m.LaserScan(
                stamp=_time_s(msg.header.stamp), frame=frame, angle_min=angle_min,
                angle_max=angle_max, angle_increment=float(msg.angle_increment),
                time_increment=float(msg.time_increment), scan_time=float(msg.scan_time),
                range_min=float(msg.range_min), range_max=float(msg.range_max),
                ranges=ranges.tobytes(), intensities=intensities.tobytes(),
                mount=m.Pose2D(x=mount.x_m, y=mount.y_m, theta=mount.theta_rad)))]
        if msgtype == "nav_msgs/msg/Odometry":
            p, tw = msg.pose.pose, msg.twist.twist
            return [(name, m.Odometry(
                stamp=_time_s(msg.header.stamp), frame=_frame(msg.header.frame_id) or "odom",
                child_frame=_frame(msg.child_frame_id) or "base_link",
                pose=m.Pose2D(x=float(p.position.x), y=float(p.position.y), theta=_yaw(p.orientation)),
                twist=m.Twist2D(vx=float(tw.linear.x), vy=float(tw.linear.y), wz=float(tw.angular.z),
                                stamp=_time_s(msg.header.stamp)),
                pose_covariance=_cov3(msg.pose.covariance), twist_covariance=_cov3(msg.twist.covariance)))]
        if msgtype == TF_TYPE:
            out: list[tuple[str, m.Message]] = []
            for tf in msg.transforms:
                parent, child = _frame(tf.header.frame_id), _frame(tf.child_frame_id)
                tr, q = tf.transform.translation, tf.transform.rotation
                pose = (float(tr.x), float(tr.y), _yaw(q))
                if parent not in ("odom", "map") and child not in ("odom", "map"):
                    fixed = (parent, Transform3D.from_ros(tf.transform))
                    if self.transforms.get(child) != fixed:  # /tf repeats a mount at its own rate
                        self.transforms[child] = fixed
                        self.mounts.clear()
                elif parent == "map" and child == "odom" and topic == "/tf":
                    out.append(("tf/map_odom", m.Transform2D(stamp=_time_s(tf.header.stamp), parent=parent,
                                                             child=child, x=pose[0], y=pose[1], theta=pose[2])))
            return out
        if msgtype == "nav_msgs/msg/OccupancyGrid":
            info = msg.info
            o = info.origin
            return [(name, m.OccupancyGrid(
                stamp=_time_s(msg.header.stamp), frame=_frame(msg.header.frame_id) or "map",
                resolution=float(info.resolution), width=int(info.width), height=int(info.height),
                origin=m.Pose2D(x=float(o.position.x), y=float(o.position.y), theta=_yaw(o.orientation)),
                data=np.asarray(msg.data, np.int8).tobytes()))]
        if msgtype == "nav_msgs/msg/Path":
            rows = np.array([[p.pose.position.x, p.pose.position.y, _yaw(p.pose.orientation)] for p in msg.poses],
                            "<f4").reshape(-1, 3)
            return [(name, m.Path(stamp=_time_s(msg.header.stamp), frame=_frame(msg.header.frame_id) or "map",
                                  poses=rows.tobytes()))]
        if msgtype == "geometry_msgs/msg/Twist":
            return [(name, m.Twist2D(vx=float(msg.linear.x), vy=float(msg.linear.y), wz=float(msg.angular.z)))]
        if msgtype == "geometry_msgs/msg/PoseWithCovarianceStamped":
            p = msg.pose.pose
            return [(name, m.PoseWithCovariance(
                stamp=_time_s(msg.header.stamp), frame=_frame(msg.header.frame_id) or "map",
                pose=m.Pose2D(x=float(p.position.x), y=float(p.position.y), theta=_yaw(p.orientation)),
                covariance=_cov3(msg.pose.covariance)))]
        if msgtype == "geometry_msgs/msg/PoseArray":
            rows = np.array([[p.position.x, p.position.y, _yaw(p.orientation)] for p in msg.poses],
                            "<f4").reshape(-1, 3)
            return [(name, m.PoseArray(stamp=_time_s(msg.header.stamp), frame=_frame(msg.header.frame_id) or "map",
                                       poses=rows.tobytes()))]
        if msgtype == "sensor_msgs/msg/Imu":
            q = msg.orientation
            roll = math.atan2(2 * (q.w * q.x + q.y * q.z), 1 - 2 * (q.x * q.x + q.y * q.y))
            pitch = math.asin(max(-1.0, min(1.0, 2 * (q.w * q.y - q.z * q.x))))
            av, la = msg.angular_velocity, msg.linear_acceleration
            return [(name, m.Imu(stamp=_time_s(msg.header.stamp), frame=_frame(msg.header.frame_id) or "imu",
                                 yaw=_yaw(q), pitch=pitch, roll=roll,
                                 angular_velocity=[float(av.x), float(av.y), float(av.z)],
                                 linear_acceleration=[float(la.x), float(la.y), float(la.z)]))]
        if msgtype == "rosgraph_msgs/msg/Clock":
            return [(name, m.Clock(stamp=_time_s(msg.clock)))]
        raise UnsupportedMessage(f"no zagv counterpart for {msgtype}")


def _yaw(q: Any) -> float:
    return quaternion_to_yaw(float(q.x), float(q.y), float(q.z), float(q.w))


def _proto_type(type_name: str) -> type[m.Message]:
    t = getattr(m, type_name, None)
    if not (isinstance(t, type) and issubclass(t, m.Message)):
        raise UnsupportedMessage(f"unknown zagv message type {type_name!r}")
    return t


def known_topics() -> list[str]:
    """zagv topics the recorder takes by default (every registered topic)."""
    return list(TOPICS)
