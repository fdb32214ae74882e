"""Real-scan localization check: AMCL on a log's real scans against a map rendered from its reference trajectory.

For a SLAM-corrected log (poses = reference trajectory): every scan is inserted into an occupancy grid at its
reference pose (``OccupancyGrid.insert_scan``, the mapper's renderer), the grid becomes a map_server-style
``OccupancyMap`` (occupied 100 where P(occ) > 0.65, free 0 where P(occ) < 0.196, else unknown), and the AMCL core
runs over the scans with the reference corrupted by ``OdometryNoise`` as odometry, starting from the first reference
pose with a 0.1 m / 0.05 rad spread. The error of each filter update's estimate against the reference is reported
(mean / RMS / max position error, RMS heading error, the share of updates more than 0.5 m off).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from services.common.map_io import FREE, OCCUPIED, UNKNOWN, OccupancyMap
from services.common.se2 import transform_points, wrap_angle
from services.localization.amcl import Amcl, AmclParams, select_beams

from .logs import LaserLog
from .occupancy import OccupancyGrid
from .odometry_noise import OdometryNoise, corrupt_poses
from .offline import scan_points


@dataclass
class LocalizationError:
    mean_m: float
    rms_m: float
    max_m: float
    rotation_rms_rad: float
    lost_fraction: float
    n_updates: int

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def render_reference_map(log: LaserLog, resolution_m: float = 0.05, max_range_m: float = 25.0) -> OccupancyMap:
    """Occupancy map of every scan inserted at its logged (reference) pose."""
    poses = np.array([s.odom_pose for s in log.scans])
    origin = log.sensor_pose[:2]
    clouds = [scan_points(log, i, max_range_m=max_range_m) for i in range(len(log.scans))]
    world = np.concatenate([poses[:, :2]] + [transform_points(pose, points)
                                             for pose, points in zip(poses, clouds, strict=True) if len(points)])
    grid = OccupancyGrid.covering(world.min(axis=0), world.max(axis=0), resolution_m)
    for pose, points in zip(poses, clouds, strict=True):
        grid.insert_scan(pose, origin, points)
    p = grid.probability()
    data = np.full(p.shape, UNKNOWN, np.int8)
    data[p > 0.65] = OCCUPIED
    data[p < 0.196] = FREE
    return OccupancyMap(data, resolution_m, (float(grid.origin_xy_m[0]), float(grid.origin_xy_m[1]), 0.0))


def localize_on_reference(log: LaserLog, noise: OdometryNoise, *, params: AmclParams | None = None,
                          grid: OccupancyMap | None = None, lost_m: float = 0.5) -> LocalizationError:
    """AMCL over the log's scans with corrupted odometry against the reference map; error per filter update."""
    params = params or AmclParams(random_seed=noise.seed)
    grid = grid or render_reference_map(log)
    reference = np.array([s.odom_pose for s in log.scans])
    odometry, _ = corrupt_poses(reference, noise)
    amcl = Amcl(grid, params, np.random.default_rng(noise.seed))
    amcl.set_initial_pose(tuple(reference[0]), np.diag([0.1**2, 0.1**2, 0.05**2]))
    mx, my, mth = (float(v) for v in log.sensor_pose)
    mount = (mx, my, mth)
    errors, turns = [], []
    for k, scan in enumerate(log.scans):
        n = len(scan.ranges_m)
        increment = float(scan.angles_rad[1] - scan.angles_rad[0]) if n > 1 else 0.0
        beams = select_beams(scan.ranges_m, float(scan.angles_rad[0]), increment, scan.min_range_m,
                             min(scan.max_range_m, 40.0), params)
        ox, oy, oth = (float(v) for v in odometry[k])
        if not amcl.process((ox, oy, oth), beams, mount) or amcl.estimate is None:
            continue
        est = np.asarray(amcl.estimate.pose, float)
        errors.append(math.hypot(est[0] - reference[k, 0], est[1] - reference[k, 1]))
        turns.append(float(wrap_angle(est[2] - reference[k, 2])))
    if not errors:
        raise ValueError("AMCL never updated (no motion past its gates?)")
    e = np.asarray(errors)
    t = np.asarray(turns)
    return LocalizationError(float(e.mean()), float(np.sqrt(np.mean(e**2))), float(e.max()),
                             float(np.sqrt(np.mean(t**2))), float(np.mean(e > lost_m)), len(e))
