"""The laser's view of the world: ranges ray-cast from the ground-truth pose and the laser mount pose.

This is the object the emulated LMS111 calls (``laser_ranges``) each time it builds a scan telegram.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from services.common.se2 import compose
from services.common.world import World
from services.sim.robot_model import SwerveRobot


@dataclass
class Body:
    """Another robot's chassis as a lidar sees it: centre (m) and radius (m)."""

    x: float
    y: float
    radius_m: float


def ray_discs(x: float, y: float, angles_rad: np.ndarray, discs: list[Body], max_range_m: float) -> np.ndarray:
    """Distance along each beam from (x, y) to the nearest disc (``max_range_m`` when none is hit). A beam whose
    origin lies inside a disc is not blocked by it (the laser never sits inside another chassis unless the
    bodies overlap, and then seeing through is the lesser evil)."""
    out = np.full(angles_rad.shape[0], max_range_m, dtype=np.float64)
    if not discs:
        return out
    dx = np.cos(angles_rad)
    dy = np.sin(angles_rad)
    for body in discs:
        cx, cy = body.x - x, body.y - y
        c2 = cx * cx + cy * cy - body.radius_m * body.radius_m
        if c2 <= 0.0 or math.sqrt(cx * cx + cy * cy) - body.radius_m >= max_range_m:
            continue
        b = dx * cx + dy * cy
        disc = b * b - c2
        hit = (disc >= 0.0) & (b > 0.0)
        if not hit.any():
            continue
        t = np.where(hit, b - np.sqrt(np.maximum(disc, 0.0)), np.inf)
        np.minimum(out, t, out=out)
    return out


class ScanSource:
    """``laser_ranges(angles)`` -> (sim stamp s, ranges m) for beam angles in the laser frame (REP-103).

    Ranges are ray-cast in ``world`` from the laser origin (robot pose composed with the mount pose
    ``mount_xytheta`` in base_link) including active dynamic obstacles; beams that hit nothing within
    ``max_range_m`` return exactly ``max_range_m``. Hits get zero-mean Gaussian noise of ``noise_std_m`` (seeded).
    ``bodies()`` gives the other robots' chassis discs at the moment of the scan (none for a lone robot).
    """

    def __init__(self, world: World, robot: SwerveRobot, now: Callable[[], float],
                 mount_xytheta: tuple[float, float, float] = (0.45, 0.0, 0.0), max_range_m: float = 20.0,
                 noise_std_m: float = 0.0, seed: int = 0) -> None:
        if not max_range_m > 0:
            raise ValueError(f"laser max range must be > 0 m, got {max_range_m}")
        self.world = world
        self.robot = robot
        self.now = now
        self.mount = tuple(float(v) for v in mount_xytheta)
        self.max_range_m = float(max_range_m)
        self.noise_std_m = float(noise_std_m)
        self._rng = np.random.default_rng(seed)
        self.scans = 0
        self.bodies: Callable[[], list[Body]] = list

    def laser_pose(self) -> tuple[float, float, float]:
        """The laser's pose in the world frame (x m, y m, theta rad)."""
        r = self.robot
        return compose((r.x, r.y, r.theta), self.mount)

    def laser_ranges(self, angles_rad: np.ndarray) -> tuple[float, np.ndarray]:
        x, y, th = self.laser_pose()
        angles = np.asarray(angles_rad, dtype=np.float64)
        try:
            ranges = self.world.raycast(x, y, angles + th, self.max_range_m)
        except ValueError as e:  # name the whole pose: a failure that repeats must be reproducible
            raise RuntimeError(f"ray casting from laser pose ({x!r}, {y!r}, {th!r}) failed: {e}") from e
        bodies = self.bodies()
        if bodies:
            np.minimum(ranges, ray_discs(x, y, angles + th, bodies, self.max_range_m), out=ranges)
        if self.noise_std_m > 0.0:
            hit = ranges < self.max_range_m
            noisy = ranges + self.noise_std_m * self._rng.standard_normal(ranges.shape[0])
            ranges = np.where(hit, np.clip(noisy, 0.0, self.max_range_m), ranges)
        self.scans += 1
        return self.now(), ranges
