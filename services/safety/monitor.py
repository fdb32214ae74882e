"""Collision monitor core (after Nav2's ``collision_monitor``): filters body-frame velocity commands against the
latest raw laser scan, whatever the planner or localization believe. No I/O; time is an argument.

The footprint is a circle of ``robot_radius_m`` r about the base origin (the paper's chassis radius), so turning in
place sweeps nothing new and only translation is ever limited. Scan points p are taken in the base frame
(mount ∘ (range cos a, range sin a)). For the commanded translation v = (vx, vy), direction u = v / |v|, a point in
the band the footprint sweeps (lateral offset h = |p × u| < r) is reached after a travel d = p·u − sqrt(r² − h²);
d_min is the least of those (the holonomic robot is judged along the way it is told to move, so a wall it drives
along, or one behind it, never stops it). Three rules, as Nav2's polygons and approach model, the most restrictive
wins:

- stop: d_min < ``stop_margin_m``: translation zeroed (rotation kept; moving away stays allowed, so the robot is
  never trapped by its own stop).
- slowdown: d_min < ``slowdown_margin_m``: translation scaled by ``slowdown_ratio``.
- approach: the footprint moved along the commanded twist, c(t) = ∫ R(wz s) v ds (exact SE(2) arcs), first
  touches a point at t_c < ``time_before_collision_s``: translation scaled by t_c / time_before_collision_s, so the
  speed falls with the distance left and the robot can always stop before contact.

Scan age (Nav2's ``source_timeout`` and ``base_shift_correction``): a scan is judged where the base is now, not
where it was when the scan was taken. With odometry poses noted around the scan's stamp, its points are moved by the
base's odometry motion since then, p_now = (⊖o_latest ⊕ o_scan) p, and the footprint is grown by the distance the
base can have gone since the newest odometry, |v| (now − t_odom). A scan is used up to ``scan_timeout_s`` old this
way; one odometry cannot carry (none noted, or not reaching back to its stamp, or odometry itself older than
``uncorrected_scan_timeout_s``) only up to ``uncorrected_scan_timeout_s``. Past that, or on a non-finite command, the
twist is zero: the monitor fails safe. A late scan under load therefore slows nothing that odometry can account for,
and a scan that stops arriving still stops the robot.

Blind sector: a 270° scanner mounted at the front cannot see behind the robot, so a back-up or a sideways move
into that wedge would be judged on no points at all. With an odometry pose at each scan, the monitor keeps a
memory (Nav2's observation persistence, in the odom frame): points within ``memory_radius_m`` of the base that
the current scan cannot see (bearing from the scanner outside its field of view) are judged with the current scan's
points. A point back in the field of view is forgotten (the scan now says what is there: turning in place, which is
never limited, clears a person who walked away), and so is one seen more than ``memory_travel_m`` of odometry
travel ago (odometry drifts with distance, not with time: a robot standing still forgets nothing).
"""

from __future__ import annotations

import bisect
import math
from collections import deque
from dataclasses import dataclass

import msgspec
import numpy as np

from services.common.clock import is_fresh
from services.common.se2 import between, interpolate_between, inverse, transform_points, wrap_angle

Pose = tuple[float, float, float]


class SafetyParams(msgspec.Struct, kw_only=True, forbid_unknown_fields=True):
    """Zones around the footprint (m), the look-ahead (s) and the scan freshness limit (s)."""

    robot_radius_m: float = 0.63
    stop_margin_m: float = 0.05
    slowdown_margin_m: float = 0.35
    slowdown_ratio: float = 0.4
    time_before_collision_s: float = 1.5
    simulation_step_s: float = 0.05
    #: a scan older than this (s) stops the robot even when odometry carries it (Nav2's ``source_timeout``)
    scan_timeout_s: float = 2.0
    #: a scan odometry cannot carry to the present stops the robot past this age (s)
    uncorrected_scan_timeout_s: float = 0.5
    #: judge a scan where the base is now, moving its points by the odometry motion since its stamp
    base_shift_correction: bool = True
    #: translation speeds below this (m/s) are passed without checks (rotation-only commands)
    min_translation_mps: float = 1e-4
    #: odometry travel (m) over which points that left the scanner's field of view are remembered (0: no memory)
    memory_travel_m: float = 5.0
    #: only points this close to the base (m) are remembered
    memory_radius_m: float = 3.0
    #: remembered points are merged on a grid of this cell (m), keeping the latest sighting
    memory_cell_m: float = 0.02

    def validate(self) -> None:
        """Raise ValueError naming the first bad parameter."""
        checks = {
            "robot_radius_m": self.robot_radius_m > 0, "stop_margin_m": self.stop_margin_m >= 0,
            "slowdown_margin_m": self.slowdown_margin_m >= self.stop_margin_m,
            "slowdown_ratio": 0 <= self.slowdown_ratio <= 1,
            "time_before_collision_s": self.time_before_collision_s > 0,
            "simulation_step_s": 0 < self.simulation_step_s <= self.time_before_collision_s,
            "scan_timeout_s": self.scan_timeout_s > 0,
            "uncorrected_scan_timeout_s": 0 < self.uncorrected_scan_timeout_s <= self.scan_timeout_s,
            "min_translation_mps": self.min_translation_mps >= 0,
            "memory_travel_m": self.memory_travel_m >= 0, "memory_radius_m": self.memory_radius_m > 0,
            "memory_cell_m": self.memory_cell_m > 0,
        }
        for name, ok in checks.items():
            value = getattr(self, name)
            if not ok or not math.isfinite(value):
                raise ValueError(f"safety parameter {name} = {value!r} is out of range")


@dataclass
class Verdict:
    """The filtered twist, what was done (``clear``/``slowdown``/``approach``/``stop``/``no_scan``), the
    translation scale applied, the clearance to the nearest point ahead (m, -1 when none) and why."""

    twist: tuple[float, float, float]
    action: str
    scale: float
    nearest_m: float
    reason: str


@dataclass(frozen=True)
class FieldOfView:
    """Where the scanner sits on the base (x m, y m, theta rad) and the bearings it sees, [angle_min, angle_max]
    (rad, scanner frame)."""

    mount: tuple[float, float, float]
    angle_min: float
    angle_max: float

    def sees(self, points: np.ndarray) -> np.ndarray:
        """Which base-frame points (n, 2) lie at a bearing the scanner covers."""
        if self.angle_max - self.angle_min >= 2 * math.pi:
            return np.ones(len(points), dtype=bool)
        local = np.asarray(transform_points(inverse(self.mount), points), dtype=np.float64).reshape(-1, 2)
        offset = np.mod(wrap_angle(np.arctan2(local[:, 1], local[:, 0]) - self.angle_min), 2 * math.pi)
        return np.asarray(offset <= self.angle_max - self.angle_min, dtype=bool)


def scan_points(ranges: np.ndarray, angle_min: float, angle_increment: float, range_min: float, range_max: float,
                mount: tuple[float, float, float]) -> np.ndarray:
    """(n, 2) base-frame points of the finite returns inside [range_min, range_max]."""
    r = np.asarray(ranges, dtype=np.float64)
    a = angle_min + np.arange(r.size) * angle_increment
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(r) & (r >= range_min) & (r <= range_max)
    r, a = r[ok], a[ok] + mount[2]
    return np.column_stack((mount[0] + r * np.cos(a), mount[1] + r * np.sin(a)))


class CollisionMonitor:
    """Holds the latest scan (base-frame points) and filters commands against it."""

    def __init__(self, params: SafetyParams) -> None:
        params.validate()
        self.params = params
        self.points = np.zeros((0, 2))
        self.scan_stamp = -math.inf
        self.memory = np.zeros((0, 2))  # odom frame (m)
        self.memory_seen_at_m = np.zeros(0)  # the odometry travel when each point was last seen (m)
        self.travelled_m = 0.0
        self.last_odom: Pose | None = None
        self.odom_stamps: deque[float] = deque()
        self.odom_poses: deque[Pose] = deque()

    def note_odom(self, stamp: float, pose: Pose) -> None:
        """An odometry pose of the base (odom frame) at ``stamp``; kept for ``scan_timeout_s`` and a second more, so
        that a scan can be placed where the base was when it was taken. A stamp behind the newest one (a clock
        restart) starts the history again."""
        if not (math.isfinite(stamp) and all(math.isfinite(v) for v in pose)):
            return
        if self.odom_stamps and stamp <= self.odom_stamps[-1]:
            if stamp == self.odom_stamps[-1]:
                return
            self.odom_stamps.clear()
            self.odom_poses.clear()
        self.odom_stamps.append(stamp)
        self.odom_poses.append(pose)
        horizon = stamp - self.params.scan_timeout_s - 1.0
        while len(self.odom_stamps) > 2 and self.odom_stamps[1] < horizon:
            self.odom_stamps.popleft()
            self.odom_poses.popleft()

    def odom_at(self, stamp: float) -> Pose | None:
        """The odometry pose at ``stamp``, interpolated between the noted poses around it; the newest pose for a
        stamp up to ``uncorrected_scan_timeout_s`` past it; None when no pose was noted that early or that late."""
        if not self.odom_stamps or not math.isfinite(stamp) or stamp < self.odom_stamps[0]:
            return None
        if stamp >= self.odom_stamps[-1]:
            if stamp - self.odom_stamps[-1] > self.params.uncorrected_scan_timeout_s:
                return None
            return self.odom_poses[-1]
        # the two noted poses around the stamp (bisection: called for every scan and command, on a history of
        # about a hundred poses, which ``se2.interpolate`` would first copy into arrays)
        i = bisect.bisect_right(self.odom_stamps, stamp)
        t0, t1 = self.odom_stamps[i - 1], self.odom_stamps[i]
        return interpolate_between(self.odom_poses[i - 1], self.odom_poses[i], (stamp - t0) / (t1 - t0))

    def base_shift(self, now: float) -> tuple[Pose, float] | None:
        """The base's odometry motion from the scan's stamp to the newest odometry pose (in the base frame at the
        scan) and the time since that pose (s); None when correction is off or odometry cannot carry the scan."""
        if not self.params.base_shift_correction or not self.odom_stamps:
            return None
        since_odom_s = now - self.odom_stamps[-1]
        if not -self.params.uncorrected_scan_timeout_s <= since_odom_s <= self.params.uncorrected_scan_timeout_s:
            return None
        at_scan = self.odom_at(self.scan_stamp)
        if at_scan is None:
            return None
        return between(at_scan, self.odom_poses[-1]), max(since_odom_s, 0.0)

    def update_scan(self, points: np.ndarray, stamp: float, odom_pose: tuple[float, float, float] | None = None,
                    view: FieldOfView | None = None) -> None:
        """The newest scan's base-frame points; with the base's odometry pose at the scan and the scanner's field of
        view, also the remembered points the scan cannot see (module docstring). Without them, the memory is
        dropped: points cannot be carried without odometry."""
        current = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        self.scan_stamp = stamp
        if odom_pose is None or view is None or self.params.memory_travel_m <= 0:
            self.memory, self.memory_seen_at_m = np.zeros((0, 2)), np.zeros(0)
            self.last_odom = None
            self.points = current
            return
        if self.last_odom is not None:
            self.travelled_m += math.hypot(odom_pose[0] - self.last_odom[0], odom_pose[1] - self.last_odom[1])
        self.last_odom = odom_pose
        remembered, seen_at_m = self._remembered(odom_pose, view)
        self.points = np.concatenate((current, remembered))
        near = np.hypot(self.points[:, 0], self.points[:, 1]) <= self.params.memory_radius_m
        self._remember(transform_points(odom_pose, self.points[near]),
                       np.concatenate((np.full(len(current), self.travelled_m), seen_at_m))[near])

    def _remembered(self, odom_pose: tuple[float, float, float], view: FieldOfView) -> tuple[np.ndarray, np.ndarray]:
        """Base-frame memory points that are near, outside the field of view and seen within ``memory_travel_m``
        of travel, with the travel at which each was seen."""
        base = np.asarray(transform_points(inverse(odom_pose), self.memory), dtype=np.float64).reshape(-1, 2)
        keep = ((self.travelled_m - self.memory_seen_at_m <= self.params.memory_travel_m)
                & (np.hypot(base[:, 0], base[:, 1]) <= self.params.memory_radius_m))
        if keep.any():
            keep[keep] = ~view.sees(base[keep])
        return base[keep], self.memory_seen_at_m[keep]

    def _remember(self, odom_points: np.ndarray, seen_at_m: np.ndarray) -> None:
        """Store points merged on a ``memory_cell_m`` grid, the latest sighting of a cell winning."""
        if odom_points.shape[0] == 0:
            self.memory, self.memory_seen_at_m = np.zeros((0, 2)), np.zeros(0)
            return
        order = np.argsort(-seen_at_m, kind="stable")
        cells = np.floor(odom_points[order] / self.params.memory_cell_m).astype(np.int64)
        # one int64 key per cell, ordered as the (column, row) pairs are (np.unique on rows sorts a structured copy,
        # several times slower): column * 2^32 + (row + 2^31), exact for |cell index| < 2^31
        keys = (cells[:, 0] << 32) + (cells[:, 1] + (1 << 31))
        _, first = np.unique(keys, return_index=True)
        pick = order[first]
        self.memory, self.memory_seen_at_m = odom_points[pick], seen_at_m[pick]

    def scan_fresh(self, now: float) -> bool:
        """Young enough to be judged on: within ``uncorrected_scan_timeout_s``, or within ``scan_timeout_s`` when
        odometry carries it to the present."""
        if is_fresh(self.scan_stamp, now, self.params.uncorrected_scan_timeout_s):
            return True
        return is_fresh(self.scan_stamp, now, self.params.scan_timeout_s) and self.base_shift(now) is not None

    def _stale(self, now: float) -> Verdict:
        age = now - self.scan_stamp
        if not math.isfinite(age):
            why = "no scan yet"
        elif age < 0:
            why = f"last scan stamped {self.scan_stamp:.2f} s, ahead of now {now:.2f} s (clock restarted)"
        elif age > self.params.scan_timeout_s:
            why = f"last scan {age:.2f} s old"
        else:
            why = f"last scan {age:.2f} s old and no odometry to carry it to the present"
        return Verdict((0.0, 0.0, 0.0), "no_scan", 0.0, -1.0, why)

    def filter(self, vx: float, vy: float, wz: float, now: float) -> Verdict:
        """The twist allowed for the command (vx, vy, wz) at time ``now``."""
        p = self.params
        if not all(math.isfinite(v) for v in (vx, vy, wz)):
            return Verdict((0.0, 0.0, 0.0), "stop", 0.0, -1.0, f"non-finite command ({vx}, {vy}, {wz})")
        if not self.scan_fresh(now):
            return self._stale(now)
        speed = math.hypot(vx, vy)
        if speed <= p.min_translation_mps or self.points.shape[0] == 0:
            return Verdict((vx, vy, wz), "clear", 1.0, -1.0, "")
        shift = self.base_shift(now)
        points, radius_m = self.points, p.robot_radius_m
        if shift is not None:
            motion, since_odom_s = shift
            points = transform_points(inverse(motion), points)
            radius_m += speed * since_odom_s
        nearest = self.travel_to_contact(vx / speed, vy / speed, points, radius_m)
        if nearest is not None and nearest < p.stop_margin_m:
            return Verdict((0.0, 0.0, wz), "stop", 0.0, nearest,
                           f"obstacle {max(nearest, 0.0):.2f} m ahead of the footprint")
        scale, action, reason = 1.0, "clear", ""
        if nearest is not None and nearest < p.slowdown_margin_m:
            scale, action = p.slowdown_ratio, "slowdown"
            reason = f"obstacle {nearest:.2f} m ahead of the footprint"
        t_c = self.time_to_contact(vx, vy, wz, points, radius_m)
        if t_c is not None:
            approach = t_c / p.time_before_collision_s
            if approach < scale:
                scale, action = approach, "approach"
                reason = f"contact in {t_c:.2f} s at the commanded speed"
        return Verdict((vx * scale, vy * scale, wz), action, scale, -1.0 if nearest is None else nearest, reason)

    def travel_to_contact(self, ux: float, uy: float, points: np.ndarray | None = None,
                          radius_m: float | None = None) -> float | None:
        """Distance (m) the footprint can translate along the unit direction (ux, uy) before it touches a point:
        min over points ahead in its swept band (lateral offset h < r) of p·u − sqrt(r² − h²); None when clear.
        A point beside the band is never reached by a translation, so a wall the robot drives along stops nothing.
        ``points`` (base frame) default to the latest scan's, ``radius_m`` to the footprint's.
        """
        r = self.params.robot_radius_m if radius_m is None else radius_m
        pts = self.points if points is None else points
        along = pts[:, 0] * ux + pts[:, 1] * uy
        lateral = pts[:, 1] * ux - pts[:, 0] * uy
        band = (np.abs(lateral) < r) & (along > -r)
        if not band.any():
            return None
        travel = along[band] - np.sqrt(r * r - lateral[band] ** 2)
        # a point already inside the footprint behind the centre is left behind by this motion
        inside_behind = (travel < 0.0) & (along[band] <= 0.0)
        travel = travel[~inside_behind]
        return float(travel.min()) if travel.size else None

    def time_to_contact(self, vx: float, vy: float, wz: float, points: np.ndarray | None = None,
                        radius_m: float | None = None) -> float | None:
        """First time (s) within the look-ahead at which a point enters the stop circle moved along the twist
        (``points`` and ``radius_m`` as in ``travel_to_contact``)."""
        p = self.params
        steps = max(1, math.ceil(p.time_before_collision_s / p.simulation_step_s))
        t = np.arange(1, steps + 1) * (p.time_before_collision_s / steps)
        # centre of the base moved by the constant twist, in the base frame at t = 0 (exact SE(2) integration)
        if abs(wz) < 1e-9:
            cx, cy = vx * t, vy * t
        else:
            s, c1 = np.sin(wz * t) / wz, (1.0 - np.cos(wz * t)) / wz
            cx, cy = s * vx - c1 * vy, c1 * vx + s * vy
        points = self.points if points is None else points
        # only points the footprint is not already touching can be contacted, and only within reach: the centre
        # moves at most |v| T along its arc, so a point farther than |v| T + r from it now is never inside the circle
        start_d2 = points[:, 0] ** 2 + points[:, 1] ** 2
        r = p.robot_radius_m if radius_m is None else radius_m
        reach_m = math.hypot(vx, vy) * float(t[-1]) + r
        points = points[(start_d2 >= r * r) & (start_d2 < reach_m * reach_m)]
        d2 = (points[None, :, 0] - cx[:, None]) ** 2 + (points[None, :, 1] - cy[:, None]) ** 2
        hit = np.nonzero((d2 < r * r).any(axis=1))[0]
        return float(t[hit[0]]) if hit.size else None
