"""What the HMI shows, computed from the latest robot messages (I/O-free).

- the robot's map pose: ``map->odom`` composed with the odometry pose when both are known (high rate, as rviz
  does), else localization's ``pose``, else the odometry pose in the odom frame;
- scan points in the frame of that pose: p = T(robot) * T(mount) * (r cos a, r sin a);
- paths and particles as flat [x0, y0, theta0, x1, ...] lists (particles decimated for display);
- a JSON-ready status in which every non-finite number is None (JSON has no NaN).
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from proto.messages import (
    LaserScan,
    NavStatus,
    OccupancyGrid,
    Odometry,
    Path,
    PoseArray,
    PoseWithCovariance,
    SafetyState,
    Transform2D,
    Twist2D,
    WheelStates,
)
from services.common.se2 import compose, robot_pose_and_frame, transform_points


def finite(v: float, digits: int = 4) -> float | None:
    """``v`` rounded, or None when it is NaN or infinite."""
    return round(float(v), digits) if math.isfinite(v) else None


def std(variance: float) -> float | None:
    """Standard deviation of a variance, or None when it is negative or not finite."""
    return finite(math.sqrt(variance)) if variance >= 0 and math.isfinite(variance) else None


def rows(payload: bytes, columns: int) -> np.ndarray:
    """float32 rows of a proto array field (zero-copy view)."""
    arr = np.frombuffer(payload, dtype="<f4")
    return arr[: len(arr) - len(arr) % columns].reshape(-1, columns)


def flat(arr: np.ndarray, digits: int = 3) -> list[float | None]:
    """A float array as a flat list with NaN/inf as None (JSON-safe)."""
    out = np.round(arr.astype(np.float64).ravel(), digits)
    if np.isfinite(out).all():
        values: list[float | None] = out.tolist()
        return values
    return [v if math.isfinite(v) else None for v in out.tolist()]


@dataclass
class RobotView:
    """The latest message of each kind, and derived display data."""

    odom: Odometry | None = None
    pose: PoseWithCovariance | None = None
    map_odom: Transform2D | None = None
    wheels: WheelStates | None = None
    nav: NavStatus | None = None
    scan: LaserScan | None = None
    path: Path | None = None
    local_plan: Path | None = None
    particles: PoseArray | None = None
    grid: OccupancyGrid | None = None
    cmd: Twist2D | None = None
    safety: SafetyState | None = None
    alive: set[str] = field(default_factory=set)
    #: when each topic's last message arrived (wall monotonic s: link health, not robot time)
    received: dict[str, float] = field(default_factory=dict)
    map_version: int = 0
    path_version: int = 0
    particles_version: int = 0

    def robot_pose(self) -> tuple[tuple[float, float, float], str] | None:
        """(pose, frame) of the robot: map frame when localization is up, else odom."""
        o, t, p = self.odom, self.map_odom, self.pose
        return robot_pose_and_frame(None if o is None else (o.pose.x, o.pose.y, o.pose.theta),
                                    None if t is None else (t.x, t.y, t.theta),
                                    None if p is None else (p.pose.x, p.pose.y, p.pose.theta))

    def map_pose(self) -> tuple[float, float, float] | None:
        found = self.robot_pose()
        if found is None or found[1] != "map":
            return None
        return found[0]

    def scan_points(self, max_points: int) -> list[float | None]:
        """Scan hits as flat [x0, y0, x1, y1, ...] in the robot pose's frame (m), at most ``max_points``."""
        found = self.robot_pose()
        if self.scan is None or found is None:
            return []
        s = self.scan
        ranges = np.frombuffer(s.ranges, dtype="<f4")
        if len(ranges) == 0:
            return []
        angles = s.angle_min + s.angle_increment * np.arange(len(ranges))
        ok = np.isfinite(ranges) & (ranges > s.range_min) & (ranges < s.range_max if s.range_max > 0 else True)
        step = max(1, int(math.ceil(int(ok.sum()) / max(1, max_points))))
        r = ranges[ok][::step].astype(np.float64)
        a = angles[ok][::step]
        mount = (s.mount.x, s.mount.y, s.mount.theta)
        pts = transform_points(compose(found[0], mount), np.stack([r * np.cos(a), r * np.sin(a)], axis=1))
        return flat(pts)

    def particle_list(self, max_points: int) -> list[float | None]:
        if self.particles is None:
            return []
        arr = rows(self.particles.poses, 3)
        step = max(1, int(math.ceil(len(arr) / max(1, max_points))))
        return flat(arr[::step])

    @staticmethod
    def path_list(path: Path | None) -> list[float | None]:
        return flat(rows(path.poses, 3)) if path is not None else []

    #: topics published continuously; the others (pose, paths, particles) legitimately pause
    STREAMING = frozenset({"odom", "wheels", "scan", "nav"})

    def stale(self, wall_now_s: float, max_age_s: float = 1.0) -> list[str]:
        """Streaming topics whose last message is older than ``max_age_s`` (a publisher that went quiet)."""
        received = tuple(self.received.items())  # one copy: the subscribers' threads add keys
        return sorted(k for k, t in received if k in self.STREAMING and wall_now_s - t > max_age_s)

    def status(self, now_s: float, clock: str, jog: dict[str, Any], wall_now_s: float | None = None) -> dict[str, Any]:
        """The JSON-ready status: odom, map pose, wheels, nav, health, jog, map, stale topics."""
        found = self.robot_pose()
        out: dict[str, Any] = {"stamp": finite(now_s, 3), "clock": clock, "jog": jog,
                     "stale": self.stale(wall_now_s) if wall_now_s is not None else [],
                     "health": sorted(self.alive), "map": {"available": self.grid is not None,
                                                           "version": self.map_version}}
        if self.odom is not None:
            o, t = self.odom.pose, self.odom.twist
            out["odom"] = {"x": finite(o.x), "y": finite(o.y), "theta": finite(o.theta), "vx": finite(t.vx),
                           "vy": finite(t.vy), "wz": finite(t.wz), "stamp": finite(self.odom.stamp, 3)}
        else:
            out["odom"] = None
        if found is not None:
            (x, y, th), frame = found
            cov = self.pose.covariance if self.pose is not None and frame == "map" else []
            out["pose"] = {"x": finite(x), "y": finite(y), "theta": finite(th), "frame": frame,
                           "std_xy_m": std(cov[0] + cov[4]) if len(cov) == 9 else None,
                           "std_theta_rad": std(cov[8]) if len(cov) == 9 else None,
                           # the filter's verdict: "localizing" until it converged, then "tracking" (or "lost")
                           "localization": self.pose.state if self.pose is not None else None}
        else:
            out["pose"] = None
        if self.wheels is not None:
            w = self.wheels
            out["wheels"] = {
                "enabled": w.enabled, "estopped": w.estopped, "link_ok": w.link_ok, "fault": w.fault,
                "loop_hz": finite(w.loop_hz, 1), "slip_residual_mps": finite(w.slip_residual_mps),
                "modules": [{"steer_rad": finite(m.steer_rad), "speed_mps": finite(m.speed_mps),
                             "steer_cmd_rad": finite(m.steer_cmd_rad), "speed_cmd_mps": finite(m.speed_cmd_mps),
                             "traction_amps": finite(m.traction_amps, 2), "fault_flags": m.fault_flags}
                            for m in w.modules]}
        else:
            out["wheels"] = None
        if self.nav is not None:
            n = self.nav
            out["nav"] = {"state": n.state, "goal_id": n.goal_id, "error": n.error,
                          "goal": {"x": finite(n.goal.x), "y": finite(n.goal.y), "theta": finite(n.goal.theta)}
                          if n.goal is not None else None,
                          "distance_left_m": finite(n.distance_left_m, 3), "recoveries": n.recoveries,
                          "sequence_id": n.sequence_id, "waypoint_index": n.waypoint_index,
                          "waypoint_count": n.waypoint_count, "sequence_paused": n.sequence_paused}
        else:
            out["nav"] = None
        if self.safety is not None:
            sf = self.safety
            out["safety"] = {"action": sf.action, "scale": finite(sf.scale, 3), "reason": sf.reason,
                             "nearest_m": finite(sf.nearest_m, 3) if sf.nearest_m >= 0 else None,
                             "interventions": sf.interventions}
        else:
            out["safety"] = None
        if self.pose is not None:
            pw = self.pose
            out["localization"] = {"state": pw.state, "match_score": finite(pw.match_score, 3),
                                   "spread_m": finite(pw.spread_m, 3)}
        else:
            out["localization"] = None
        return out


class VelocityRecorder:
    """Commanded (cmd_vel) and measured (odom twist) body velocities sampled at a fixed rate.

    Each row: (t_s, cmd_vx, cmd_vy, cmd_wz, meas_vx, meas_vy, meas_wz) in s, m/s, rad/s. A command older than
    ``cmd_hold_s`` counts as zero (drive stops on a silent cmd_vel too).
    """

    COLUMNS = ("t_s", "cmd_vx_mps", "cmd_vy_mps", "cmd_wz_radps", "meas_vx_mps", "meas_vy_mps", "meas_wz_radps")

    def __init__(self, history_s: float, rate_hz: float, cmd_hold_s: float = 0.5) -> None:
        self.rows: collections.deque[tuple[float, ...]] = collections.deque(maxlen=int(history_s * rate_hz) + 1)
        self.cmd_hold_s = cmd_hold_s

    def sample(self, now_s: float, cmd: Twist2D | None, cmd_at_s: float, odom: Odometry | None) -> tuple[float, ...]:
        c = (cmd.vx, cmd.vy, cmd.wz) if cmd is not None and now_s - cmd_at_s <= self.cmd_hold_s else (0.0, 0.0, 0.0)
        m = (odom.twist.vx, odom.twist.vy, odom.twist.wz) if odom is not None else (math.nan,) * 3
        row = (round(now_s, 3), *c, *m)
        self.rows.append(row)
        return row

    def window(self, seconds: float) -> list[tuple[float, ...]]:
        if not self.rows:
            return []
        t_end = self.rows[-1][0]
        return [r for r in self.rows if r[0] >= t_end - seconds]

    def csv(self) -> str:
        lines = [",".join(self.COLUMNS)]
        for r in self.rows:
            lines.append(",".join("" if not math.isfinite(v) else f"{v:.4f}" for v in r))
        return "\n".join(lines) + "\n"
