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

No scan newer than ``scan_timeout_s`` (or a non-finite command) gives a zero twist: the monitor fails safe.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import msgspec
import numpy as np


class SafetyParams(msgspec.Struct, kw_only=True, forbid_unknown_fields=True):
    """Zones around the footprint (m), the look-ahead (s) and the scan freshness limit (s)."""

    robot_radius_m: float = 0.63
    stop_margin_m: float = 0.05
    slowdown_margin_m: float = 0.35
    slowdown_ratio: float = 0.4
    time_before_collision_s: float = 1.5
    simulation_step_s: float = 0.05
    scan_timeout_s: float = 0.5
    #: translation speeds below this (m/s) are passed without checks (rotation-only commands)
    min_translation_mps: float = 1e-4

    def validate(self) -> None:
        """Raise ValueError naming the first bad parameter."""
        checks = {
            "robot_radius_m": self.robot_radius_m > 0, "stop_margin_m": self.stop_margin_m >= 0,
            "slowdown_margin_m": self.slowdown_margin_m >= self.stop_margin_m,
            "slowdown_ratio": 0 <= self.slowdown_ratio <= 1,
            "time_before_collision_s": self.time_before_collision_s > 0,
            "simulation_step_s": 0 < self.simulation_step_s <= self.time_before_collision_s,
            "scan_timeout_s": self.scan_timeout_s > 0, "min_translation_mps": self.min_translation_mps >= 0,
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

    def update_scan(self, points: np.ndarray, stamp: float) -> None:
        self.points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        self.scan_stamp = stamp

    def scan_fresh(self, now: float) -> bool:
        return now - self.scan_stamp <= self.params.scan_timeout_s

    def filter(self, vx: float, vy: float, wz: float, now: float) -> Verdict:
        """The twist allowed for the command (vx, vy, wz) at time ``now``."""
        p = self.params
        if not all(math.isfinite(v) for v in (vx, vy, wz)):
            return Verdict((0.0, 0.0, 0.0), "stop", 0.0, -1.0, f"non-finite command ({vx}, {vy}, {wz})")
        if not self.scan_fresh(now):
            age = now - self.scan_stamp
            why = "no scan yet" if not math.isfinite(age) else f"last scan {age:.2f} s old"
            return Verdict((0.0, 0.0, 0.0), "no_scan", 0.0, -1.0, why)
        speed = math.hypot(vx, vy)
        if speed <= p.min_translation_mps or self.points.shape[0] == 0:
            return Verdict((vx, vy, wz), "clear", 1.0, -1.0, "")
        nearest = self.travel_to_contact(vx / speed, vy / speed)
        if nearest is not None and nearest < p.stop_margin_m:
            return Verdict((0.0, 0.0, wz), "stop", 0.0, nearest,
                           f"obstacle {max(nearest, 0.0):.2f} m ahead of the footprint")
        scale, action, reason = 1.0, "clear", ""
        if nearest is not None and nearest < p.slowdown_margin_m:
            scale, action = p.slowdown_ratio, "slowdown"
            reason = f"obstacle {nearest:.2f} m ahead of the footprint"
        t_c = self.time_to_contact(vx, vy, wz)
        if t_c is not None:
            approach = t_c / p.time_before_collision_s
            if approach < scale:
                scale, action = approach, "approach"
                reason = f"contact in {t_c:.2f} s at the commanded speed"
        return Verdict((vx * scale, vy * scale, wz), action, scale, -1.0 if nearest is None else nearest, reason)

    def travel_to_contact(self, ux: float, uy: float) -> float | None:
        """Distance (m) the footprint can translate along the unit direction (ux, uy) before it touches a point:
        min over points ahead in its swept band (lateral offset h < r) of p·u − sqrt(r² − h²); None when clear.
        A point beside the band is never reached by a translation, so a wall the robot drives along stops nothing.
        """
        r = self.params.robot_radius_m
        pts = self.points
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

    def time_to_contact(self, vx: float, vy: float, wz: float) -> float | None:
        """First time (s) within the look-ahead at which a point enters the stop circle moved along the twist."""
        p = self.params
        steps = max(1, math.ceil(p.time_before_collision_s / p.simulation_step_s))
        t = np.arange(1, steps + 1) * (p.time_before_collision_s / steps)
        # centre of the base moved by the constant twist, in the base frame at t = 0 (exact SE(2) integration)
        if abs(wz) < 1e-9:
            cx, cy = vx * t, vy * t
        else:
            s, c1 = np.sin(wz * t) / wz, (1.0 - np.cos(wz * t)) / wz
            cx, cy = s * vx - c1 * vy, c1 * vx + s * vy
        points = self.points
        # only points the footprint is not already touching can be contacted
        start_d2 = points[:, 0] ** 2 + points[:, 1] ** 2
        r = p.robot_radius_m
        points = points[start_d2 >= r * r]
        d2 = (points[None, :, 0] - cx[:, None]) ** 2 + (points[None, :, 1] - cy[:, None]) ** 2
        hit = np.nonzero((d2 < r * r).any(axis=1))[0]
        return float(t[hit[0]]) if hit.size else None
