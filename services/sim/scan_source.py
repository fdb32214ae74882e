"""The laser's view of the world: ranges ray-cast from the ground-truth pose and the laser mount pose.

This is the object the emulated LMS111 calls (``laser_ranges``) each time it builds a scan telegram.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from services.common.se2 import compose
from services.sim.robot_model import SwerveRobot
from services.sim.world import World


class ScanSource:
    """``laser_ranges(angles)`` -> (sim stamp s, ranges m) for beam angles in the laser frame (REP-103).

    Ranges are ray-cast in ``world`` from the laser origin (robot pose composed with the mount pose
    ``mount_xytheta`` in base_link) including active dynamic obstacles; beams that hit nothing within
    ``max_range_m`` return exactly ``max_range_m``. Hits get zero-mean Gaussian noise of ``noise_std_m`` (seeded).
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

    def laser_pose(self) -> tuple[float, float, float]:
        """The laser's pose in the world frame (x m, y m, theta rad)."""
        r = self.robot
        return compose((r.x, r.y, r.theta), self.mount)

    def laser_ranges(self, angles_rad: np.ndarray) -> tuple[float, np.ndarray]:
        x, y, th = self.laser_pose()
        angles = np.asarray(angles_rad, dtype=np.float64)
        ranges = self.world.raycast(x, y, angles + th, self.max_range_m)
        if self.noise_std_m > 0.0:
            hit = ranges < self.max_range_m
            noisy = ranges + self.noise_std_m * self._rng.standard_normal(ranges.shape[0])
            ranges = np.where(hit, np.clip(noisy, 0.0, self.max_range_m), ranges)
        self.scans += 1
        return self.now(), ranges
