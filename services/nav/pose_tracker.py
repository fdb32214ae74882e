"""The robot's map pose as nav drives on it, from localization and odometry.

The high-rate map pose is ``map->odom ⊕ odom`` (``tf/map_odom`` composed with the odometry pose); without a
transform, the last ``pose`` is moved on by the odometry since it arrived (``pose ⊕ (odom_at_pose⁻¹ ⊕ odom)``).
The last ``history_s`` of odometry is kept so that a scan is placed with the pose at the time its beams were taken
(``at``), not when it arrived: a scan processed 50 ms late while turning at 0.5 rad/s would put a wall 2.5 m away
6 cm off. ``scan_observation`` places a scan's beams on the line between the sensor poses at its first and last beam.
"""

from __future__ import annotations

import bisect
import math
from collections import deque

import numpy as np

from proto import codec
from proto import messages as m
from services.common.se2 import Pose2, compose, inverse, wrap_angle
from services.nav.costmap import ScanObservation

Pose = Pose2


class PoseTracker:
    """Map pose from ``tf/map_odom``, ``pose`` and ``odom`` (module docstring)."""

    def __init__(self, history_s: float = 2.0) -> None:
        self.history_s = history_s
        self.odom_history: deque[tuple[float, Pose]] = deque()
        self.odom: Pose | None = None
        self.odom_stamp = -math.inf
        self.map_odom: Pose | None = None
        self.pose: Pose | None = None
        self.pose_stamp = -math.inf
        self.tf_stamp = -math.inf
        self.odom_at_pose: Pose | None = None
        #: localization's verdict on its last pose (``tracking`` is the only one nav drives on)
        self.loc_state = "tracking"
        self.loc_detail = ""
        #: localization's uncertainty of its last pose (PoseWithCovariance fields of the same names)
        self.position_std_m = 0.0
        self.weakest_axis_rad = 0.0
        self.heading_std_rad = 0.0
        #: the particle cloud's std along its widest position direction (from ``covariance``), for the logs
        self.particle_std_m = 0.0

    def on_odom(self, msg: m.Odometry) -> None:
        p = (msg.pose.x, msg.pose.y, msg.pose.theta)
        if all(math.isfinite(v) for v in p):
            self.odom, self.odom_stamp = p, msg.stamp
            h = self.odom_history
            if h and msg.stamp < h[-1][0]:
                h.clear()  # time went back (a restarted simulator)
            h.append((msg.stamp, p))
            while h and h[0][0] < msg.stamp - self.history_s:
                h.popleft()

    def odom_at(self, stamp: float) -> Pose | None:
        """Odometry pose at ``stamp``, linearly interpolated (theta along the shorter arc); None outside the
        history."""
        h = self.odom_history
        if not h or not h[0][0] <= stamp <= h[-1][0]:
            return None
        k = bisect.bisect_left(h, stamp, key=lambda e: e[0])
        t1, b = h[k]
        if k == 0 or t1 == stamp:
            return b
        t0, a = h[k - 1]
        f = (stamp - t0) / (t1 - t0) if t1 > t0 else 1.0
        dth = wrap_angle(b[2] - a[2])
        return (a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1]), a[2] + f * dth)

    def at(self, stamp: float) -> Pose | None:
        """The map pose at ``stamp`` (map->odom composed with the odometry then); the current pose when the
        odometry history does not cover ``stamp``."""
        odom = self.odom_at(stamp)
        if odom is None or self.map_odom is None:
            return self.current()
        return compose(self.map_odom, odom)

    def on_tf(self, msg: m.Transform2D) -> tuple[float, float] | None:
        """Take a map->odom transform; the jump it made the current pose do, (metres, radians), or None when
        there was no pose before or after."""
        before = self.current()
        p = (msg.x, msg.y, msg.theta)
        if all(math.isfinite(v) for v in p):
            self.map_odom, self.tf_stamp = p, msg.stamp
        after = self.current()
        if before is None or after is None:
            return None
        return math.hypot(after[0] - before[0], after[1] - before[1]), abs(wrap_angle(after[2] - before[2]))

    def on_pose(self, msg: m.PoseWithCovariance) -> None:
        p = (msg.pose.x, msg.pose.y, msg.pose.theta)
        self.loc_state = msg.state
        self.loc_detail = f"scan match {msg.match_score:.2f}, spread {msg.spread_m:.2f} m"
        self.position_std_m, self.weakest_axis_rad = msg.position_std_m, msg.weakest_axis_rad
        self.heading_std_rad = msg.heading_std_rad
        if len(msg.covariance) == 9 and all(math.isfinite(v) for v in msg.covariance):
            c = msg.covariance
            self.particle_std_m = math.sqrt(max(float(np.linalg.eigvalsh([[c[0], c[1]], [c[3], c[4]]])[-1]), 0.0))
        if all(math.isfinite(v) for v in p):
            self.pose, self.pose_stamp = p, msg.stamp
            self.odom_at_pose = self.odom

    def current(self) -> Pose | None:
        if self.map_odom is not None and self.odom is not None:
            return compose(self.map_odom, self.odom)
        if self.pose is not None and self.odom is not None and self.odom_at_pose is not None:
            return compose(self.pose, compose(inverse(self.odom_at_pose), self.odom))
        return self.pose

    def last_update(self) -> float:
        """Stamp of the older of the two sources nav drives on: odometry, and localization (``pose`` or
        ``tf/map_odom``, which localization publishes with every scan it uses). A hung drive, lidar or
        localization therefore makes the pose stale and stops the robot (never driving blind on odometry)."""
        return min(self.odom_stamp, max(self.pose_stamp, self.tf_stamp))

    def scan_observation(self, msg: m.LaserScan) -> ScanObservation | None:
        """The scan's beams in the map frame: the sensor pose at the first and the last beam (``at`` ⊕ mount),
        beams in between on the line between them; None for an empty scan or before any pose."""
        ranges = codec.array(msg, "ranges")
        if not msg.angle_increment or ranges.size == 0:
            return None
        duration = msg.time_increment * (ranges.size - 1) if msg.time_increment > 0 else 0.0
        mount = (msg.mount.x, msg.mount.y, msg.mount.theta)
        at_first, at_last = self.at(msg.stamp), self.at(msg.stamp + duration)
        if at_first is None or at_last is None:
            return None
        first, last = compose(at_first, mount), compose(at_last, mount)
        f = np.linspace(0.0, 1.0, ranges.size)
        dth = wrap_angle(last[2] - first[2])
        xs = first[0] + f * (last[0] - first[0])
        ys = first[1] + f * (last[1] - first[1])
        angles = first[2] + f * dth + msg.angle_min + np.arange(ranges.size) * msg.angle_increment
        return ScanObservation(xs, ys, angles, ranges, msg.range_min, msg.range_max)
