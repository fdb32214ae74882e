"""What the front end takes from a scan's far end, on synthetic worlds ray-cast exactly with an LMS-like 180° / 1°
laser: a CARMEN FLASER log's "no return" code (the scanner's range limit written for nothing hit) is found from the
readings and never treated as a hit; walls up to ``match_max_range_m`` (40 m) away are matched, so a robot in a hall
whose walls are all beyond 20 m is placed by its scans instead of by its odometry; and points beyond
``match_full_weight_range_m`` weigh (r₀/r)² in the match."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.common.se2 import between, compose
from services.common.world import World
from services.localization.slam.likelihood import MultiResolutionGrid
from services.localization.slam.logs import CARMEN_MAX_RANGE_M, no_return_range_m, parse_carmen
from services.localization.slam.mapper import GraphSlam, SlamConfig
from services.localization.slam.matcher import refine
from services.localization.slam.offline import run_slam
from services.localization.synthetic import Laser

BEAMS = 181
#: the LMS's "no return" reading in its 8 m mode
NO_RETURN_M = 8.19


def _world(free: list[list[float]], obstacles: list[list[float]] | None = None) -> World:
    rects = np.array(free, float)
    extent = (rects[:, 0].min() - 1, rects[:, 1].min() - 1, rects[:, 2].max() + 1, rects[:, 3].max() + 1)
    return World.from_rectangles("hall", 0.05, list(extent), rects.tolist(), obstacles or [])


def _flaser_log(world: World, truth: list[np.ndarray], odom: list[np.ndarray], range_max_m: float,
                no_return_m: float | None) -> list[str]:
    """FLASER lines (181 beams over 180°) of scans taken at ``truth`` with ``odom`` as the logged odometry; beams
    that hit nothing within ``range_max_m`` read ``no_return_m`` (or are left out of range: ``range_max_m``)."""
    laser = Laser(world, beams=BEAMS, fov_rad=math.pi, range_max=range_max_m, noise_m=0.005,
                  rng=np.random.default_rng(3))
    lines = []
    for k, (t, o) in enumerate(zip(truth, odom)):
        ranges = laser.scan(tuple(t), (0.0, 0.0, 0.0)).astype(float)
        ranges[~np.isfinite(ranges)] = no_return_m if no_return_m is not None else range_max_m + 1.0
        values = " ".join(f"{r:.2f}" for r in ranges)
        lines.append(f"FLASER {BEAMS} {values} {t[0]} {t[1]} {t[2]} {o[0]} {o[1]} {o[2]} {k + 1.0} host {k + 1.0}")
    return lines


def _drive(n_steps: int, step_m: float, scale_error: float) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """True poses ``step_m`` apart along x from (-n·step/2, 0, 0) and the odometry with ``scale_error``."""
    truth = [np.array([-0.5 * n_steps * step_m + step_m * k, 0.02 * k, 0.0]) for k in range(n_steps + 1)]
    odom = [truth[0]]
    for a, b in zip(truth, truth[1:]):
        step = between(a, b)
        step[:2] *= 1.0 + scale_error
        odom.append(compose(odom[-1], step))
    return truth, odom


def _final_error_m(lines: list[str], config: SlamConfig | None = None, *, max_range_m: float | None = None) -> float:
    log = parse_carmen(lines)
    if max_range_m is not None:
        for scan in log.scans:
            scan.max_range_m = max_range_m
    slam = run_slam(log, config).slam
    truth = np.array([float(v) for v in lines[-1].split()[2 + BEAMS:5 + BEAMS]])
    return float(np.hypot(*between(truth, slam.current_pose())[:2]))


def test_no_return_code_is_the_recurring_largest_reading():
    readings = np.concatenate([np.full(50, 8.19), np.full(20, 8.18), np.linspace(0.5, 7.9, 1000)])
    assert no_return_range_m(readings) == pytest.approx(8.18)
    assert no_return_range_m(np.linspace(0.5, 30.0, 1000)) is None  # a largest reading seen once is a hit
    assert no_return_range_m(np.array([np.nan, np.inf])) is None
    world = _world([[-6.0, -3.0, 6.0, 3.0]])
    truth, odom = _drive(4, 0.5, 0.0)
    coded = parse_carmen(_flaser_log(world, truth, odom, range_max_m=5.0, no_return_m=NO_RETURN_M))
    assert all(s.max_range_m < NO_RETURN_M for s in coded.scans)
    plain = parse_carmen(_flaser_log(world, truth[:1], odom[:1], range_max_m=20.0, no_return_m=None))
    assert plain.scans[0].max_range_m == CARMEN_MAX_RANGE_M


def test_no_return_readings_are_no_phantom_wall_that_holds_the_match_back():
    """A 14 x 10 m room seen in the 8 m mode: beams towards the far walls read the code. Taken for hits, the code
    draws an arc around the robot that moves with it and drags the scan-to-submap match (the odometry is 10 % short,
    0.6 m over the route): the result is worse than dead reckoning. Dropped, the room's walls place the robot."""
    world = _world([[-7.0, -5.0, 7.0, 5.0]], obstacles=[[-2.0, 3.5, -1.0, 5.0], [2.0, -5.0, 3.0, -4.0]])
    truth, odom = _drive(12, 0.5, -0.10)
    lines = _flaser_log(world, truth, odom, range_max_m=NO_RETURN_M, no_return_m=NO_RETURN_M)
    dropped = _final_error_m(lines)
    as_hits = _final_error_m(lines, max_range_m=CARMEN_MAX_RANGE_M)
    assert dropped < 0.3, dropped  # 0.19 m: the odometry prior keeps part of the scale error
    assert as_hits > 0.6 and as_hits > 3 * dropped, (dropped, as_hits)


def test_walls_beyond_twenty_metres_place_the_robot_in_a_hall():
    """Every wall of the hall is 22 m or more from the path: with matching cut at 20 m the scans have no points and
    the 10 % scale error of the odometry (0.8 m over the route) stays in the pose; matched out to 40 m the far walls
    take about half of it out (0.41 m left: far points weigh (20/r)², and the odometry prior holds its share)."""
    world = _world([[-30.0, -25.0, 30.0, 25.0]], obstacles=[[-30.0, 22.0, -26.0, 25.0], [26.0, -25.0, 30.0, -21.0]])
    truth, odom = _drive(8, 1.0, -0.10)
    lines = _flaser_log(world, truth, odom, range_max_m=50.0, no_return_m=None)
    far = _final_error_m(lines, SlamConfig(match_max_range_m=40.0))
    near = _final_error_m(lines, SlamConfig(match_max_range_m=20.0))
    assert near > 0.7, near
    assert far < 0.6 * near, (far, near)


def test_far_points_weigh_less_and_a_zero_weight_drops_a_point():
    slam = GraphSlam(SlamConfig(match_full_weight_range_m=20.0))
    slam._sensor_origin = np.array([0.5, 0.0])
    weights = slam._point_weights(np.array([[10.5, 0.0], [20.5, 0.0], [40.5, 0.0]]))
    np.testing.assert_allclose(weights, [1.0, 1.0, 0.25])
    rng = np.random.default_rng(4)
    wall = np.stack([np.full(80, 3.0), np.linspace(-2.0, 2.0, 80)], axis=1)
    side = np.stack([np.linspace(-1.0, 2.0, 60), np.full(60, 2.0)], axis=1)
    grid = MultiResolutionGrid.from_points(np.concatenate([wall, side]), 0.05, 3)
    scan = np.concatenate([wall, side])[::2] - [0.04, 0.03]
    outliers = rng.uniform(-2.0, 2.0, (40, 2))  # points that fit nowhere, at zero weight they do not count
    weighted = refine(grid, np.concatenate([scan, outliers]), np.zeros(3),
                      point_weights=np.concatenate([np.ones(len(scan)), np.zeros(len(outliers))]))
    alone = refine(grid, scan, np.zeros(3))
    np.testing.assert_allclose(weighted.pose, alone.pose, atol=1e-9)
