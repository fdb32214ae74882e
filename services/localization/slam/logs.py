"""Readers for 2-D laser logs with odometry: CARMEN ``.clf`` text logs, ROS 1 ``.bag`` files and ROS 2 bags.

CARMEN: ``FLASER n r_1..r_n x y theta odom_x odom_y odom_theta ipc_timestamp hostname logger_timestamp``
(beams from -90° at CARMEN's ``carmen_laser_get_angle_increment``: 1° for 180 and 181 beams, 0.5° for 360 and 361,
0.25° for 400 and 401, else spread evenly over 180°; a 180- or 360-beam scan thus ends one step short of +90°; the
laser sits ``PARAM robot_frontlaser_offset`` m ahead of the robot, 0 when absent; FLASER gives no range limit, so the
log's "no return" code, its largest reading when that recurs, is found from the readings: ``no_return_range_m``) and
``ROBOTLASER1 type start_angle fov resolution max_range
accuracy remission_mode n r_1..r_n m rem_1..rem_m laser_x laser_y laser_theta robot_x robot_y robot_theta
tv rv forward_safety side_safety turn_axis ipc_timestamp hostname logger_timestamp`` (the mount is
``robot_pose⁻¹ ⊕ laser_pose``); a log with neither (raw records only) is read from its ``RAWLASER1 type start_angle
fov resolution max_range accuracy remission_mode n r_1..r_n m rem_1..rem_m ipc_timestamp ...`` front-laser lines,
each placed at the odometry of its ``ODOM x y theta tv rv accel ipc_timestamp ...`` lines interpolated at its stamp
(a log that has FLASER or ROBOTLASER1 lines uses those: its RAWLASER1 lines are the same scans); the stamp is the
IPC timestamp. CARMEN records stay in file order (the logger
writes them in time order); a log whose stamps do not increase strictly (some published logs carry truncated or
zero stamps) gets its scan index as stamp and ``stamps_from_log = False``.
Bags: ``sensor_msgs/LaserScan`` (header stamps) with odometry from ``nav_msgs/Odometry`` (or ``/tf`` odom→base),
interpolated at each scan stamp, and the laser mount from ``/tf_static`` (composed along its chain of frames; a laser
hung upside down has its scans re-expressed upright: ``services/common/laser_mount.py``).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from services.common.laser_mount import Transform3D, planar_mount, upright_scan
from services.common.se2 import between, compose, interpolate, inverse, wrap_angle

from .evaluation import match_stamps

CARMEN_MAX_RANGE_M = 80.0
#: a log's largest reading is the laser's "no return" code when it recurs: at least this many times and this fraction
#: of all readings (the SICK LMS reports nothing hit as its range limit, 8.191 / 32.767 / 81.91 m by mode)
NO_RETURN_MIN_COUNT = 10
NO_RETURN_MIN_FRACTION = 1e-4
#: readings within this fraction below the largest one belong to the no-return code (it may be written 51.14 / 51.15)
NO_RETURN_BAND = 0.02
#: a laser further than this from the robot frame is a malformed record, not a mount
MAX_MOUNT_OFFSET_M = 2.0


@dataclass
class LaserScanRecord:
    """One scan: ``ranges_m`` at ``angles_rad`` (laser frame), odometry pose of the robot (x, y, theta)."""

    stamp_s: float
    ranges_m: np.ndarray
    angles_rad: np.ndarray
    odom_pose: np.ndarray
    min_range_m: float = 0.0
    max_range_m: float = CARMEN_MAX_RANGE_M


@dataclass
class LaserLog:
    """Scans in time order and the laser's pose (x, y, theta) in the robot frame."""

    scans: list[LaserScanRecord]
    sensor_pose: np.ndarray = field(default_factory=lambda: np.zeros(3))
    stamps_from_log: bool = True

    @property
    def duration_s(self) -> float:
        return self.scans[-1].stamp_s - self.scans[0].stamp_s if self.scans else 0.0


def flaser_angle_increment_rad(n_beams: int) -> float:
    """Beam spacing of an n-beam FLASER scan, as CARMEN's ``carmen_laser_get_angle_increment`` defines it (the
    SICK LMS modes: 1°, 0.5°, 0.25°; an even count is the odd one without its last beam)."""
    for full, step_deg in ((181, 1.0), (361, 0.5), (401, 0.25)):
        if n_beams in (full, full - 1):
            return float(np.radians(step_deg))
    return float(np.pi / max(n_beams - 1, 1))


def no_return_range_m(ranges_m: np.ndarray) -> float | None:
    """The reading an FLASER log writes for "no return", or None when it has none: the smallest centimetre value
    within ``NO_RETURN_BAND`` below the log's largest reading that occurs at least ``NO_RETURN_MIN_COUNT`` times and
    on ``NO_RETURN_MIN_FRACTION`` of all readings. FLASER lines do not give the scanner's range limit, and treating
    that code as a hit puts a phantom wall at the range limit that moves with the robot (it holds the scan match
    back to the prediction)."""
    ranges_m = np.asarray(ranges_m, float)
    ranges_m = ranges_m[np.isfinite(ranges_m)]
    if len(ranges_m) == 0:
        return None
    top = float(ranges_m.max())
    values, counts = np.unique(np.round(ranges_m[ranges_m >= top * (1.0 - NO_RETURN_BAND)], 2), return_counts=True)
    repeated = values[counts >= max(NO_RETURN_MIN_COUNT, NO_RETURN_MIN_FRACTION * len(ranges_m))]
    return float(repeated.min()) if len(repeated) else None


def parse_carmen(lines: Iterable[str]) -> LaserLog:
    """Scans of a CARMEN log's front laser, in file order: its ROBOTLASER1 and FLASER lines (a FLASER line with the
    stamp of a ROBOTLASER1 line is the same scan written twice, and only the ROBOTLASER1 one, with its mount and
    range limit, is kept), else its RAWLASER1 lines with the ODOM lines' odometry (the same scans again, when the
    others exist). Other lines, the rear laser's included, are ignored."""
    scans: list[LaserScanRecord] = []  # FLASER and ROBOTLASER1
    robot_stamps: list[float] = []  # of the ROBOTLASER1 lines
    kinds: list[str] = []  # the record kind of each of ``scans``
    front_offset_m = 0.0
    mounts: list[np.ndarray] = []
    raw_scans: list[LaserScanRecord] = []
    odometry: list[tuple[float, float, float, float]] = []  # (stamp, x, y, theta) of the ODOM lines
    odometry_before: list[int] = []  # per RAWLASER1 line: the ODOM line last read before it (-1: none yet)
    for number, line in enumerate(lines, start=1):
        fields = line.split()
        if not fields:
            continue
        try:
            if fields[0] == "PARAM" and len(fields) > 2 and fields[1] == "robot_frontlaser_offset":
                front_offset_m = float(fields[2])
            elif fields[0] == "FLASER":
                n = int(fields[1])
                ranges = np.array(fields[2:2 + n], float)
                rest = fields[2 + n:]
                odom = np.array(rest[3:6], float)
                stamp = float(rest[6])
                angles = -np.pi / 2 + np.arange(n) * flaser_angle_increment_rad(n)
                scans.append(LaserScanRecord(stamp, ranges, angles, odom))
                kinds.append("FLASER")
            elif fields[0] == "RAWLASER1":  # the front laser's own record: no pose, odometry from ODOM lines
                start, fov, max_range = float(fields[2]), float(fields[3]), float(fields[5])
                n = int(fields[8])
                ranges = np.array(fields[9:9 + n], float)
                n_rem = int(fields[9 + n])
                stamp = float(fields[10 + n + n_rem])
                angles = start + np.arange(n) * (fov / max(n - 1, 1))
                raw_scans.append(LaserScanRecord(stamp, ranges, angles, np.zeros(3), max_range_m=max_range))
                odometry_before.append(len(odometry) - 1)
            elif fields[0] == "ODOM":
                odometry.append((float(fields[7]), float(fields[1]), float(fields[2]), float(fields[3])))
            elif fields[0] == "ROBOTLASER1":
                start, fov, max_range = float(fields[2]), float(fields[3]), float(fields[5])
                n = int(fields[8])
                ranges = np.array(fields[9:9 + n], float)
                n_rem = int(fields[9 + n])
                rest = fields[10 + n + n_rem:]
                laser = np.array(rest[0:3], float)
                odom = np.array(rest[3:6], float)
                stamp = float(rest[11])
                angles = start + np.arange(n) * (fov / max(n - 1, 1))
                scans.append(LaserScanRecord(stamp, ranges, angles, odom, max_range_m=max_range))
                kinds.append("ROBOTLASER1")
                robot_stamps.append(stamp)
                mounts.append(between(odom, laser))
        except (ValueError, IndexError) as exc:
            raise ValueError(f"CARMEN log line {number}: malformed {fields[0]} record ({exc})") from exc
    if robot_stamps and "FLASER" in kinds:  # FLASER lines too: drop those that repeat a ROBOTLASER1 line
        _, repeated = match_stamps(np.array(robot_stamps), np.array([s.stamp_s for s in scans]), 1e-3)
        scans = [s for s, kind, again in zip(scans, kinds, repeated, strict=True) if kind != "FLASER" or not again]
    if not scans and raw_scans:  # a log of raw laser and odometry records only
        scans = _with_odometry(raw_scans, odometry, odometry_before)
    sensor_pose = np.array([front_offset_m, 0.0, 0.0])
    if mounts:
        mount = np.median(np.array(mounts), axis=0)
        if np.hypot(mount[0], mount[1]) > MAX_MOUNT_OFFSET_M:
            raise ValueError(f"CARMEN ROBOTLASER1 laser pose is {np.hypot(mount[0], mount[1]):.1f} m from the robot "
                             f"pose: not a mount offset (more than {MAX_MOUNT_OFFSET_M} m)")
        sensor_pose = mount
    flaser = [s for s in scans if s.max_range_m == CARMEN_MAX_RANGE_M]
    code = no_return_range_m(np.concatenate([s.ranges_m for s in flaser])) if flaser else None
    if code is not None:
        for scan in flaser:  # readings from 5 mm below the code count as no return (scan_to_points keeps r < max)
            scan.max_range_m = code - 0.005
    stamps = np.array([s.stamp_s for s in scans])
    from_log = bool(len(stamps) < 2 or np.all(np.diff(stamps) > 0))
    if not from_log:
        for k, scan in enumerate(scans):
            scan.stamp_s = float(k)
    return LaserLog(scans, sensor_pose, from_log)


def _with_odometry(raw_scans: list[LaserScanRecord], odometry: list[tuple[float, float, float, float]],
                   odometry_before: list[int]) -> list[LaserScanRecord]:
    """RAWLASER1 scans with the ODOM pose interpolated at each scan's stamp; scans before the first or after the last
    ODOM record are left out (their odometry is unknown). When the stamps cannot order the records (zero or
    truncated: scans or ODOM lines whose stamps do not increase), each scan takes the ODOM line read last before it
    in the file (the logger writes in time order), or the first one after it at the start of the log."""
    if not odometry:
        raise ValueError(f"CARMEN log has {len(raw_scans)} RAWLASER1 scans but no ODOM record to place them")
    table = np.array(odometry, float)
    scan_stamps = np.array([s.stamp_s for s in raw_scans])
    if not (np.all(np.diff(scan_stamps) > 0) and np.all(np.diff(table[:, 0]) > 0)):
        for scan, before in zip(raw_scans, odometry_before, strict=True):
            scan.odom_pose = table[max(before, 0), 1:].copy()
        return raw_scans
    inside = [s for s in raw_scans if table[0, 0] <= s.stamp_s <= table[-1, 0]]
    if not inside:
        raise ValueError(f"CARMEN log: none of its {len(raw_scans)} RAWLASER1 scans lies within the time of its ODOM "
                         f"records ({table[0, 0]:.3f}-{table[-1, 0]:.3f} s)")
    poses = interpolate(table[:, 0], table[:, 1:], np.array([s.stamp_s for s in inside]))
    for scan, pose in zip(inside, poses, strict=True):
        scan.odom_pose = pose
    return inside


def with_mount(log: LaserLog, sensor_pose: np.ndarray) -> LaserLog:
    """The same log re-expressed for a laser mounted at ``sensor_pose``: every odometry pose x becomes
    x ⊕ s ⊕ s'⁻¹ so that the laser poses (x ⊕ s) and the scans are unchanged; only the robot frame moves."""
    sensor_pose = np.asarray(sensor_pose, float)
    shift = compose(log.sensor_pose, inverse(sensor_pose))
    scans = [LaserScanRecord(s.stamp_s, s.ranges_m, s.angles_rad, compose(s.odom_pose, shift), s.min_range_m,
                             s.max_range_m) for s in log.scans]
    return LaserLog(scans, sensor_pose.copy(), log.stamps_from_log)


def _yaw(q) -> float:
    return float(np.arctan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z)))


def _stamp(header) -> float:
    return header.stamp.sec + header.stamp.nanosec * 1e-9


def read_bag(path: Path, scan_topic: str | None = None, odom_topic: str | None = None) -> LaserLog:
    """Scans and odometry of a ROS 1 (or ROS 2) bag, read with ``rosbags`` (no ROS installation needed)."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    # a ROS 2 bag that does not carry its message definitions (sqlite3 before Iron) is read with Humble's
    with AnyReader([Path(path)], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
        scan_conns = [c for c in reader.connections if c.msgtype == "sensor_msgs/msg/LaserScan"
                      and (scan_topic is None or c.topic == scan_topic)]
        if not scan_conns:
            raise ValueError(f"{path}: no sensor_msgs/LaserScan topic{f' {scan_topic}' if scan_topic else ''}")
        scan_conns = scan_conns[:1]
        odom_conns = [c for c in reader.connections if c.msgtype == "nav_msgs/msg/Odometry"
                      and (odom_topic is None or c.topic == odom_topic)][:1]
        tf_conns = [c for c in reader.connections if c.topic in ("/tf", "/tf_static")]
        raw_scans: list[Any] = []
        odom_stamps: list[float] = []
        odom_poses: list[tuple[float, float, float]] = []
        tf_odom: list[tuple[float, float, float, float]] = []
        static: dict[str, tuple[str, Transform3D]] = {}
        dynamic: dict[str, tuple[str, Transform3D]] = {}
        base_frames: list[str] = []
        for conn, _, raw in reader.messages(connections=scan_conns + odom_conns + tf_conns):
            msg: Any = reader.deserialize(raw, conn.msgtype)
            if conn in scan_conns:
                raw_scans.append(msg)
            elif conn in odom_conns:
                p = msg.pose.pose
                if not base_frames and msg.child_frame_id:
                    base_frames.append(msg.child_frame_id.lstrip("/"))
                odom_stamps.append(_stamp(msg.header))
                odom_poses.append((p.position.x, p.position.y, _yaw(p.orientation)))
            else:
                for tf in msg.transforms:
                    t, q = tf.transform.translation, tf.transform.rotation
                    child, parent = tf.child_frame_id.lstrip("/"), tf.header.frame_id.lstrip("/")
                    transform = Transform3D.from_ros(tf.transform)
                    if conn.topic == "/tf_static":
                        static[child] = (parent, transform)
                    elif parent == "odom":
                        if not odom_conns:
                            tf_odom.append((_stamp(tf.header), t.x, t.y, _yaw(q)))
                            if not base_frames:
                                base_frames.append(child)
                    elif child not in dynamic:
                        dynamic[child] = (parent, transform)  # a mount some bags publish on /tf, not /tf_static
    if not odom_stamps:
        if not tf_odom:
            raise ValueError(f"{path}: no nav_msgs/Odometry topic and no odom transform in /tf")
        tf_odom.sort()
        odom_stamps = [row[0] for row in tf_odom]
        odom_poses = [row[1:] for row in tf_odom]
    o_stamps = np.asarray(odom_stamps)
    order = np.argsort(o_stamps, kind="stable")
    o_stamps = o_stamps[order]
    o_poses = np.asarray(odom_poses, float)[order]
    laser_frame = raw_scans[0].header.frame_id.lstrip("/") if raw_scans else ""
    try:
        mount = planar_mount(laser_frame, {**dynamic, **static}, base_frames[0] if base_frames else None)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None
    sensor_pose = mount.pose
    scans = []
    for msg in raw_scans:
        stamp = _stamp(msg.header)
        ranges = np.asarray(msg.ranges, float)
        angle_min = float(msg.angle_min)
        if mount.upside_down:  # the scan as the upright one it equals (services/common/laser_mount.py)
            angle_min, ranges = upright_scan(angle_min, float(msg.angle_increment), ranges)
        angles = angle_min + np.arange(len(ranges)) * msg.angle_increment
        odom = interpolate(o_stamps, o_poses, stamp)[0]
        scans.append(LaserScanRecord(stamp, ranges, angles, odom, float(msg.range_min), float(msg.range_max)))
    scans.sort(key=lambda s: s.stamp_s)
    sensor_pose[2] = float(wrap_angle(sensor_pose[2]))
    return LaserLog(scans, sensor_pose)


def read_log(path: str | Path) -> LaserLog:
    """A ``.clf`` (CARMEN, optionally ``.gz``) or ``.bag`` log, or a ROS 2 bag (its folder, or a ``.mcap`` /
    ``.db3`` file in it next to its ``metadata.yaml``)."""
    path = Path(path)
    if path.is_dir() and (path / "metadata.yaml").is_file():
        return read_bag(path)
    if not path.is_file():
        raise FileNotFoundError(f"log not found: {path}")
    if path.suffix == ".bag":
        return read_bag(path)
    if path.suffix in (".mcap", ".db3"):
        if not (path.parent / "metadata.yaml").is_file():
            raise ValueError(f"{path}: a ROS 2 bag file is read with the metadata.yaml of its folder, and "
                             f"{path.parent} has none")
        return read_bag(path.parent)
    if path.name.endswith((".clf", ".log", ".clf.gz", ".log.gz")):
        if path.suffix == ".gz":
            import gzip

            with gzip.open(path, "rt") as f:
                return parse_carmen(f)
        with path.open() as f:
            return parse_carmen(f)
    raise ValueError(f"unsupported log format {path.name!r}: expected a CARMEN .clf/.log, a ROS 1 .bag or a ROS 2 "
                     f"bag folder")
