"""The laser mount is applied right in every SLAM path: the same laser poses and the same ranges, recorded once by
a laser on the robot's origin and once by one mounted 0.25 m ahead, 0.1 m left and turned 0.3 rad, give the same
laser trajectory and the same map in live mapping (front end, back end, incremental render), and the real-scan
localization check localizes such a log. A mapper told the wrong mount does not (the check can fail)."""

from __future__ import annotations

import math

import numpy as np

from services.common.se2 import compose, inverse
from services.common.world import World
from services.localization.mapping import grid_to_map
from services.localization.slam.evaluation import scan_poses
from services.localization.slam.live import LiveMapper
from services.localization.slam.localization_check import localize_on_reference
from services.localization.slam.logs import LaserLog, LaserScanRecord
from services.localization.slam.map_compare import occupied_f1
from services.localization.slam.mapper import scan_to_points
from services.localization.slam.odometry_noise import OdometryNoise
from services.localization.synthetic import Laser, route

ROTATED_MOUNT = np.array([0.25, 0.1, 0.3])
#: laser poses along the lobby and into the main corridor of the corridor world
LASER_ROUTE = [(0.3, 0.0, 0.0), (4.0, 0.1, 0.0), (4.0, 0.1, math.pi / 2), (4.0, 3.2, 0.0), (9.0, 3.2, 0.0)]


def _recording(mount: np.ndarray):
    """(robot poses, ranges, angles) of the route's laser poses for a laser at ``mount`` (noise-free ranges: the
    two recordings hold the same numbers, up to the rounding of robot pose ∘ mount: that can flip a beam which
    grazes a cell corner of the world's raster)."""
    laser = Laser(World.load_builtin("corridor"), beams=541, fov_rad=math.radians(270.0), range_max=20.0, noise_m=0.0)
    lasers = np.array(list(route(LASER_ROUTE, step_m=0.05, step_rad=0.05)))
    robots = compose(lasers, np.broadcast_to(inverse(mount), lasers.shape))
    ranges = [laser.scan(tuple(r), tuple(mount)) for r in robots]
    return lasers, robots, ranges, laser.angles


def _live_map(robots, ranges, angles, mount_told: np.ndarray):
    mapper = LiveMapper(start_pose=tuple(robots[0]))
    for k, (pose, r) in enumerate(zip(robots, ranges, strict=True)):
        points = scan_to_points(r, angles, mount_told, min_range_m=0.05, max_range_m=20.0)
        mapper.add_scan(0.04 * k, pose, points, mount_told[:2])
    _, trajectory = mapper.trajectory()
    return scan_poses(trajectory, mount_told), grid_to_map(mapper.render())


def test_live_mapping_gives_the_same_laser_path_and_map_whatever_the_mount():
    lasers, robots0, ranges0, angles = _recording(np.zeros(3))
    _, robots1, ranges1, _ = _recording(ROTATED_MOUNT)
    differ = sum(int(np.count_nonzero(~np.isclose(a, b, rtol=0.0, atol=1e-6))) for a, b in zip(ranges0, ranges1,
                                                                                                  strict=True))
    assert differ <= 1e-4 * len(ranges0) * angles.size, differ  # the same scans but for beams grazing a corner
    path0, map0 = _live_map(robots0, ranges0, angles, np.zeros(3))
    path1, map1 = _live_map(robots1, ranges1, angles, ROTATED_MOUNT)
    error0 = np.hypot(*(path0[:, :2] - lasers[:, :2]).T)
    error1 = np.hypot(*(path1[:, :2] - lasers[:, :2]).T)
    apart = np.hypot(*(path1[:, :2] - path0[:, :2]).T)
    print(f"\nlaser path error: max {error0.max():.3f} m (mount 0), {error1.max():.3f} m (rotated mount); the two "
          f"paths {np.sqrt(np.mean(apart**2)):.3f} m RMS apart")
    assert error0.max() < 0.1 and error1.max() < 0.1  # SLAM's own drift over 12 m; a misapplied mount: decimetres
    assert np.sqrt(np.mean(apart**2)) < 0.03
    same = occupied_f1(map1.data >= 65, map1.resolution, map1.origin[:2], map0.data >= 65, map0.resolution,
                       map0.origin[:2])
    assert same.f1 > 0.9, same  # both maps in the world frame (anchored at the robot's start pose)
    # the check can fail: the mounted recording read as if the laser sat on the robot's origin
    wrong_path, wrong_map = _live_map(robots1, ranges1, angles, np.zeros(3))
    wrong = occupied_f1(wrong_map.data >= 65, wrong_map.resolution, wrong_map.origin[:2], map0.data >= 65,
                        map0.resolution, map0.origin[:2])
    wrong_error = np.hypot(*(wrong_path[:, :2] - lasers[:, :2]).T)
    print(f"map F1 against the mount-0 map: {same.f1:.3f} (rotated mount), {wrong.f1:.3f} (mount ignored); "
          f"laser path error with the mount ignored: max {wrong_error.max():.3f} m")
    assert wrong.f1 < 0.5 * same.f1, (wrong, same)
    assert wrong_error.max() > 0.2


def test_real_scan_localization_check_applies_the_mount():
    lasers, robots, ranges, angles = _recording(ROTATED_MOUNT)
    scans = [LaserScanRecord(0.04 * k, np.asarray(r, float), angles, pose, 0.05, 20.0)
             for k, (pose, r) in enumerate(zip(robots[::2], ranges[::2], strict=True))]
    log = LaserLog(scans, ROTATED_MOUNT.copy())
    error = localize_on_reference(log, OdometryNoise.for_reference(seed=3))
    assert error.rms_m < 0.05 and error.lost_fraction == 0.0, error
