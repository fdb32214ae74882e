"""Live mapping on the synthetic corridor (the built-in corridor world, ray-cast; odometry with a scale error):
shared by the tests and the bench, no I/O beyond reading the world file."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from services.common.world import World
from services.localization.synthetic import Laser, Odometry, route

from .live import LiveMapper
from .mapper import scan_to_points

#: lobby, then the main corridor to x = 15 m (start at the world's start pose)
CORRIDOR_ROUTE = [(0.0, 0.0, 0.0), (4.0, 0.1, 0.0), (4.0, 0.1, math.pi), (-1.0, 0.1, math.pi),
                  (-1.0, 0.3, math.pi / 2), (0.0, 3.2, 0.0), (15.0, 3.2, 0.0), (15.0, 3.2, math.pi),
                  (6.0, 3.2, math.pi)]
SCAN_PERIOD_S = 0.04
MOUNT = (0.3, 0.0, 0.0)


@dataclass
class LiveRun:
    mapper: LiveMapper
    world: World
    scans: int
    cpu_s_per_processed_scan: float
    cpu_s_max: float
    errors_m: np.ndarray  # map-pose error of every scan after the first


def run_corridor(speed_mps: float = 1.0, waypoints: list[tuple[float, float, float]] | None = None, *, beams: int = 361,
                 fov_rad: float = math.pi, render_every_scans: int = 0) -> LiveRun:
    """Drive ``waypoints`` at ``speed_mps`` with a 25 Hz LMS111-like laser (180°, 0.5°) and feed ``LiveMapper``;
    the map is rendered every ``render_every_scans`` scans (0: never) as the service does."""
    world = World.load_builtin("corridor")
    laser = Laser(world, beams=beams, fov_rad=fov_rad, range_max=20.0, rng=np.random.default_rng(3))
    truth = list(route(waypoints or CORRIDOR_ROUTE, step_m=speed_mps * SCAN_PERIOD_S, step_rad=0.04))
    odom = Odometry(truth[0], scale_error=0.01, noise_frac=0.01)
    mapper = LiveMapper(start_pose=truth[0])
    cpu, cpu_max, errors = 0.0, 0.0, []
    for i, pose in enumerate(truth):
        o = np.array(odom.step(pose) if i else odom.pose)
        points = scan_to_points(laser.scan(pose, MOUNT), laser.angles, np.array(MOUNT), min_range_m=0.05,
                                max_range_m=20.0)
        t0 = time.thread_time()
        processed = mapper.add_scan(i * SCAN_PERIOD_S, o, points, np.array(MOUNT[:2]))
        dt = time.thread_time() - t0
        if processed:
            cpu += dt
            cpu_max = max(cpu_max, dt)
        if render_every_scans and i % render_every_scans == 0:
            mapper.render()
        est = mapper.pose_at(o)
        if i and est is not None:
            errors.append(math.hypot(est[0] - pose[0], est[1] - pose[1]))
    return LiveRun(mapper, world, len(truth), cpu / max(mapper.processed, 1), cpu_max, np.array(errors))
