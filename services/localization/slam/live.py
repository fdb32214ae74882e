"""Incremental SLAM for the live mapping mode: motion gates in front of ``GraphSlam`` and the map -> odom transform.

Like slam_toolbox's ``minimum_travel_distance`` / ``minimum_travel_heading``, a scan is processed only when the
odometry moved at least ``min_travel_m`` or turned ``min_turn_rad`` since the last processed scan; between processed
scans the map pose is ``map_odom ∘ odom`` with ``map_odom = slam_pose ∘ odom⁻¹`` of the last processed scan. The map
frame is anchored by ``start_pose`` (the robot's map pose at the first scan). Pending loop constraints are optimised
at least every ``optimize_every_keyframes`` keyframes. ``trajectory()`` gives every scan fed, as ``GraphSlam``'s
does offline: a skipped scan sits at ``x_k ⊕ (o_k⁻¹ ⊕ o)`` from the last processed scan k (odometry o), so it
follows the optimisation too.
"""

from __future__ import annotations

import numpy as np

from services.common.se2 import between, compose, inverse, transform_points, wrap_angle

from .mapper import GraphSlam, SlamConfig
from .occupancy import OccupancyGrid


def grow_to_cover(grid: OccupancyGrid, points: np.ndarray, margin_m: float = 5.0) -> OccupancyGrid:
    """``grid`` itself when it holds ``points`` (N, 2) with a one-cell border, else a larger copy (``margin_m`` more
    on each side that had to grow) with the old log-odds in place."""
    res = grid.resolution_m
    h, w = grid.log_odds.shape
    lo_have = grid.origin_xy_m
    hi_have = grid.origin_xy_m + np.array([w, h]) * res
    lo_need, hi_need = points.min(axis=0) - res, points.max(axis=0) + res
    if np.all(lo_need >= lo_have) and np.all(hi_need <= hi_have):
        return grid
    grow_lo = np.where(lo_need < lo_have, np.ceil((lo_have - lo_need + margin_m) / res), 0).astype(int)
    grow_hi = np.where(hi_need > hi_have, np.ceil((hi_need - hi_have + margin_m) / res), 0).astype(int)
    log_odds = np.zeros((h + grow_lo[1] + grow_hi[1], w + grow_lo[0] + grow_hi[0]), np.float32)
    log_odds[grow_lo[1]:grow_lo[1] + h, grow_lo[0]:grow_lo[0] + w] = grid.log_odds
    return OccupancyGrid(log_odds, grid.origin_xy_m - grow_lo * res, res, grid.log_odds_occupied,
                         grid.log_odds_free, grid.clamp)


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
        #: skipped scans: (stamp_s, index of the last processed scan in GraphSlam, odometry step since it)
        self._skipped_scans: list[tuple[float, int, np.ndarray]] = []
        self._optimized_at_keyframes = 0
        self._loops_at_optimize = 0
        self._grid: OccupancyGrid | None = None
        self._rendered_poses: np.ndarray | None = None
        self.rebuild_angle_rad = 0.005
        self.full_renders = 0

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
            self.note_skipped(stamp_s, odom_pose)
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

    def note_skipped(self, stamp_s: float, odom_pose: np.ndarray) -> None:
        """A scan the motion gates kept from the matcher: placed by odometry from the last processed scan."""
        self.skipped += 1
        if self._last_odom is not None:
            step = between(self._last_odom, np.asarray(odom_pose, float))
            self._skipped_scans.append((float(stamp_s), self.slam.n_scans - 1, step))

    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """(stamps_s (N,), robot poses (N, 3)) of every scan fed, processed or skipped, in stamp order, from the
        current graph (the trajectory ``zagv map build`` writes, and ``zagv map eval --trajectory`` reads)."""
        stamps, poses = self.slam.trajectory() if self.slam.n_scans else (np.zeros(0), np.zeros((0, 3)))
        if self._skipped_scans:
            skipped_stamps = np.array([t for t, _, _ in self._skipped_scans])
            anchors = np.array([k for _, k, _ in self._skipped_scans], dtype=np.intp)
            steps = np.array([d for _, _, d in self._skipped_scans])
            stamps = np.concatenate([stamps, skipped_stamps])
            poses = np.vstack([poses, compose(poses[anchors], steps)])
        order = np.argsort(stamps, kind="stable")
        return stamps[order], poses[order].reshape(-1, 3)

    def pose_at(self, odom_pose: np.ndarray) -> np.ndarray | None:
        """Map pose for an odometry pose (``map_odom ∘ odom``); None before the first scan."""
        if self.map_odom is None:
            return None
        return compose(self.map_odom, np.asarray(odom_pose, float))

    def render(self) -> OccupancyGrid | None:
        """Log-odds grid from every keyframe at its optimised pose (None before the first scan).

        Incremental: new keyframes are inserted into the last grid (grown when they reach past it); the grid is
        rebuilt from scratch only when optimisation moved an inserted keyframe by more than half a cell or
        ``rebuild_angle_rad``."""
        slam = self.slam
        n = slam.n_keyframes
        if n == 0:
            return None
        poses = slam.graph.poses()
        res = slam.config.resolution_m
        if self._grid is not None and self._rendered_poses is not None:
            old = self._rendered_poses
            moved = np.hypot(*(poses[:len(old), :2] - old[:, :2]).T)
            turned = np.abs(wrap_angle(poses[:len(old), 2] - old[:, 2]))
            if moved.max(initial=0.0) > 0.5 * res or turned.max(initial=0.0) > self.rebuild_angle_rad:
                self._grid = None
        if self._grid is None:
            self._grid = slam.render_map()
            self.full_renders += 1
        else:
            assert self._rendered_poses is not None
            for k in range(len(self._rendered_poses), n):
                kf = slam._keyframes[k]
                if not len(kf.map_points):
                    continue
                world = transform_points(poses[k], kf.map_points)
                self._grid = grow_to_cover(self._grid, np.vstack([world, poses[k:k + 1, :2]]))
                self._grid.insert_scan(poses[k], kf.sensor_origin_xy_m, kf.map_points)
        self._rendered_poses = poses.copy()
        return self._grid
