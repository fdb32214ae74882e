"""Incremental SLAM for the live mapping mode: motion gates in front of ``GraphSlam`` and the map -> odom transform.

Like slam_toolbox's ``minimum_travel_distance`` / ``minimum_travel_heading``, a scan is processed only when the
odometry moved at least ``min_travel_m`` or turned ``min_turn_rad`` since the last processed scan; between processed
scans the map pose is ``map_odom ∘ odom`` with ``map_odom = slam_pose ∘ odom⁻¹`` of the last processed scan. The map
frame is anchored by ``start_pose`` (the robot's map pose at the first scan). Pending loop constraints are optimised
at least every ``optimize_every_keyframes`` keyframes.
"""

from __future__ import annotations

import numpy as np

from .mapper import GraphSlam, SlamConfig
from .occupancy import OccupancyGrid
from .se2 import between, compose, inverse, wrap_angle


class LiveMapper:
    """Feed ``(stamp, odom pose, robot-frame hit points)``; read ``pose``, ``map_odom`` and ``render()``."""

    def __init__(self, config: SlamConfig | None = None, *, start_pose: tuple[float, float, float] = (0.0, 0.0, 0.0),
                 min_travel_m: float = 0.1, min_turn_rad: float = 0.1, optimize_every_keyframes: int = 10) -> None:
        self.slam = GraphSlam(config)
        self.start_pose = np.asarray(start_pose, float)
        self.min_travel_m = min_travel_m
        self.min_turn_rad = min_turn_rad
        self.optimize_every_keyframes = optimize_every_keyframes
        self._anchor: np.ndarray | None = None  # map pose of the odom frame's origin fed to GraphSlam
        self._last_odom: np.ndarray | None = None
        self.map_odom: np.ndarray | None = None
        self.pose: np.ndarray | None = None
        self.processed = 0
        self.skipped = 0
        self._optimized_at_keyframes = 0
        self._loops_at_optimize = 0

    def moved_enough(self, odom_pose: np.ndarray) -> bool:
        if self._last_odom is None:
            return True
        d = between(self._last_odom, np.asarray(odom_pose, float))
        return bool(np.hypot(d[0], d[1]) >= self.min_travel_m or abs(float(wrap_angle(d[2]))) >= self.min_turn_rad)

    def add_scan(self, stamp_s: float, odom_pose: np.ndarray, points: np.ndarray,
                 sensor_origin_xy_m: np.ndarray) -> bool:
        """Process one scan if the robot moved past the gates; True when it was processed."""
        odom_pose = np.asarray(odom_pose, float)
        if not self.moved_enough(odom_pose):
            self.skipped += 1
            return False
        if self._anchor is None:
            self._anchor = compose(self.start_pose, inverse(odom_pose))
        pose = self.slam.add_scan(stamp_s, compose(self._anchor, odom_pose), points, sensor_origin_xy_m)
        self._last_odom = odom_pose
        self.processed += 1
        n_kf = self.slam.n_keyframes
        loops = len(self.slam.loop_closures)
        if loops > self._loops_at_optimize and n_kf - self._optimized_at_keyframes >= self.optimize_every_keyframes:
            self.slam.optimize()
            self._optimized_at_keyframes, self._loops_at_optimize = n_kf, loops
            pose = self.slam.current_pose()
        self.pose = pose
        self.map_odom = compose(pose, inverse(odom_pose))
        return True

    def pose_at(self, odom_pose: np.ndarray) -> np.ndarray | None:
        """Map pose for an odometry pose (``map_odom ∘ odom``); None before the first scan."""
        if self.map_odom is None:
            return None
        return compose(self.map_odom, np.asarray(odom_pose, float))

    def render(self) -> OccupancyGrid | None:
        """Log-odds grid from every keyframe at its optimised pose (None before the first scan)."""
        if self.slam.n_keyframes == 0:
            return None
        return self.slam.render_map()
