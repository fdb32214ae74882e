"""What the site's fleet view knows of each robot, computed from the robots' own messages (I/O-free).

Every robot publishes under ``agv/<robot_id>/``; the site hears them all through its router. Per robot:

- present while at least one of its health tokens (``agv/<id>/@health/<service>``) reaches the site; the view
  records when it left (its last token went: the robot stopped, or its link to the site dropped) and came back;
- its map pose: ``map->odom`` composed with the odometry pose when both are known (as the robot's own HMI does),
  else localization's ``pose``, else the odometry pose (frame ``odom``);
- its path (decimated), navigation state and goal, drive state, battery and faults.

Times are wall-clock seconds passed in by the caller (presence is about the link, not the robot's clock).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from proto.messages import (
    NavStatus,
    OccupancyGrid,
    Odometry,
    Path,
    PoseWithCovariance,
    SafetyState,
    Transform2D,
    WheelStates,
)
from services.common.se2 import robot_pose_and_frame

#: topic (after ``agv/<id>/``) -> attribute of RobotTrack it updates
TOPICS: dict[str, str] = {"odom": "odom", "tf/map_odom": "map_odom", "pose": "pose", "wheels": "wheels",
                          "nav/status": "nav", "nav/path": "path", "safety/state": "safety", "map": "grid"}
#: latched topics: their last value is asked for whenever a robot (re)appears at the site
LATCHED = ("tf/map_odom", "pose", "nav/status", "nav/path", "safety/state", "map")
#: how many presence events the view keeps
EVENTS_KEPT = 50


def finite(v: float, digits: int = 4) -> float | None:
    """``v`` rounded, or None when it is NaN or infinite (JSON has no NaN)."""
    return round(float(v), digits) if math.isfinite(v) else None


def battery_percent(volts: float, empty_v: float, full_v: float) -> float:
    """Charge (%) linear in the battery voltage: 100 (v - empty_v) / (full_v - empty_v), clipped to 0..100."""
    return round(min(100.0, max(0.0, 100.0 * (volts - empty_v) / (full_v - empty_v))), 1)


def decimated_path(path: Path | None, max_points: int) -> list[float | None]:
    """The path's (x, y) as a flat list [x0, y0, x1, ...], at most ``max_points`` points, the last one kept."""
    if path is None or not path.poses:
        return []
    xy = np.frombuffer(path.poses, dtype="<f4")
    xy = xy[: len(xy) - len(xy) % 3].reshape(-1, 3)[:, :2].astype(np.float64)
    if len(xy) > max_points:
        keep = np.unique(np.linspace(0, len(xy) - 1, max_points).round().astype(int))
        xy = xy[keep]
    return [finite(v, 3) for v in xy.ravel().tolist()]


@dataclass
class RobotTrack:
    """The latest message of each kind from one robot, and its presence at the site."""

    robot_id: str
    odom: Odometry | None = None
    map_odom: Transform2D | None = None
    pose: PoseWithCovariance | None = None
    wheels: WheelStates | None = None
    nav: NavStatus | None = None
    path: Path | None = None
    safety: SafetyState | None = None
    grid: OccupancyGrid | None = None
    services: set[str] = field(default_factory=set)
    joined_at_s: float | None = None
    left_at_s: float | None = None
    leaves: int = 0

    @property
    def present(self) -> bool:
        return bool(self.services)

    def map_pose(self) -> tuple[tuple[float, float, float], str] | None:
        """(pose, frame): the map pose when localization is known, else the odometry pose in ``odom``."""
        o, t, p = self.odom, self.map_odom, self.pose
        return robot_pose_and_frame(None if o is None else (o.pose.x, o.pose.y, o.pose.theta),
                                    None if t is None else (t.x, t.y, t.theta),
                                    None if p is None else (p.pose.x, p.pose.y, p.pose.theta))

    def faults(self) -> list[str]:
        """Everything an operator must know is wrong, in words."""
        out: list[str] = []
        if not self.present:
            out.append("offline: no health token of this robot reaches the site")
        w = self.wheels
        if w is not None:
            if w.estopped:
                out.append("e-stop")
            if w.fault:
                out.append(f"drive: {w.fault}")
            if not w.link_ok:
                out.append("drive: CAN link down")
            out += [f"module {i}: fault flags 0x{m.fault_flags:02x}" for i, m in enumerate(w.modules) if m.fault_flags]
        if self.nav is not None and self.nav.state == "failed":
            out.append(f"nav: {self.nav.error or 'goal failed'}")
        if self.pose is not None and self.pose.state == "lost":
            out.append("localization lost")
        if self.safety is not None and self.safety.action in ("stop", "no_scan"):
            out.append(f"safety: {self.safety.action}" + (f" ({self.safety.reason})" if self.safety.reason else ""))
        return out


@dataclass
class FleetView:
    """Every robot the site hears, keyed by robot id; ``own_id`` (the fleet service's own) is never a robot."""

    own_id: str = "site"
    robots_shown: list[str] = field(default_factory=list)
    map_from: str = ""
    robots: dict[str, RobotTrack] = field(default_factory=dict)
    events: list[dict[str, Any]] = field(default_factory=list)
    map_version: int = 0
    _map_source: tuple[str, int] | None = None

    def accepts(self, robot_id: str) -> bool:
        return robot_id != self.own_id and (not self.robots_shown or robot_id in self.robots_shown)

    def track(self, robot_id: str) -> RobotTrack | None:
        if not self.accepts(robot_id):
            return None
        if robot_id not in self.robots:
            self.robots[robot_id] = RobotTrack(robot_id)
        return self.robots[robot_id]

    def on_message(self, robot_id: str, topic: str, msg: Any) -> None:
        """Store ``msg``, the latest on ``agv/<robot_id>/<topic>`` (a key of TOPICS)."""
        t = self.track(robot_id)
        if t is None:
            return
        setattr(t, TOPICS[topic], msg)
        if topic == "map":
            self._choose_map()

    def on_health(self, robot_id: str, service: str, up: bool, now_s: float) -> str | None:
        """A health token came or went; returns ``"joined"`` / ``"left"`` when the robot's presence changed."""
        t = self.track(robot_id)
        if t is None:
            return None
        was = t.present
        (t.services.add if up else t.services.discard)(service)
        change = None
        if t.present and not was:
            t.joined_at_s, change = now_s, "joined"
        elif was and not t.present:
            t.left_at_s, change = now_s, "left"
            t.leaves += 1
        if change:
            self.events.append({"robot_id": robot_id, "event": change, "wall_s": round(now_s, 3)})
            del self.events[:-EVENTS_KEPT]
        return change

    def _choose_map(self) -> None:
        ids = [self.map_from] if self.map_from else sorted(self.robots)
        for rid in ids:
            t = self.robots.get(rid)
            if t is not None and t.grid is not None:
                source = (rid, id(t.grid))
                if source != self._map_source:
                    self._map_source = source
                    self.map_version += 1
                return

    def site_map(self) -> tuple[str, OccupancyGrid] | None:
        """(robot id, grid) of the site map, or None before any robot published one."""
        if self._map_source is None:
            return None
        rid = self._map_source[0]
        grid = self.robots[rid].grid
        return (rid, grid) if grid is not None else None

    def robot_json(self, t: RobotTrack, radius_m: float, battery_v: tuple[float, float], path_max_points: int
                   ) -> dict[str, Any]:
        found = t.map_pose()
        out: dict[str, Any] = {"id": t.robot_id, "present": t.present, "services": sorted(t.services),
                               "leaves": t.leaves, "footprint": {"radius_m": radius_m}, "faults": t.faults()}
        if found is not None:
            (x, y, th), frame = found
            out["pose"] = {"x": finite(x), "y": finite(y), "theta": finite(th), "frame": frame}
        else:
            out["pose"] = None
        n = t.nav
        out["nav"] = {"state": n.state, "goal_id": n.goal_id, "error": n.error,
                      "distance_left_m": finite(n.distance_left_m, 3),
                      "goal": {"x": finite(n.goal.x), "y": finite(n.goal.y), "theta": finite(n.goal.theta)}
                      if n.goal is not None else None,
                      "waypoint_index": n.waypoint_index, "waypoint_count": n.waypoint_count} if n else None
        w = t.wheels
        out["drive"] = {"enabled": w.enabled, "estopped": w.estopped, "link_ok": w.link_ok} if w else None
        volts = max((m.battery_v for m in w.modules if math.isfinite(m.battery_v)), default=0.0) if w else 0.0
        out["battery"] = {"voltage_v": round(volts, 2), "percent": battery_percent(volts, *battery_v)} \
            if volts > 0 else None
        out["localization"] = t.pose.state if t.pose is not None else None
        out["path"] = decimated_path(t.path, path_max_points)
        return out

    def snapshot(self, radius_m: float, battery_v: tuple[float, float], path_max_points: int) -> dict[str, Any]:
        """The JSON-ready state of the site: every robot (sorted by id), the map version and recent events."""
        site_map = self.site_map()
        return {"robots": [self.robot_json(self.robots[rid], radius_m, battery_v, path_max_points)
                           for rid in sorted(self.robots)],
                "map": {"version": self.map_version, "from": site_map[0] if site_map else None},
                "events": self.events[-10:]}
