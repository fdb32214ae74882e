"""LiveMapper on the synthetic corridor: motion gates, map -> odom, incremental map rendering, map quality."""

from __future__ import annotations

import math

import numpy as np

from services.localization.mapping import grid_to_map
from services.localization.slam.live import LiveMapper, grow_to_cover
from services.localization.slam.live_synthetic import run_corridor
from services.localization.slam.map_compare import best_aligned_f1, occupied_f1, surface
from services.localization.slam.occupancy import OccupancyGrid


def test_gates_skip_small_motions_and_map_odom_composes():
    mapper = LiveMapper(min_travel_m=0.1, min_turn_rad=0.1, start_pose=(1.0, 2.0, math.pi / 2))
    rng = np.random.default_rng(0)
    wall = np.stack([np.full(200, 3.0), np.linspace(-3, 3, 200)], axis=1) + rng.normal(0, 0.005, (200, 2))
    assert mapper.add_scan(0.0, np.array([5.0, 5.0, 0.0]), wall, np.zeros(2))
    # the map frame starts at start_pose whatever the odometry says
    assert np.allclose(mapper.pose, (1.0, 2.0, math.pi / 2))
    assert not mapper.add_scan(0.1, np.array([5.05, 5.0, 0.0]), wall, np.zeros(2))
    assert not mapper.add_scan(0.2, np.array([5.0, 5.0, 0.05]), wall, np.zeros(2))
    assert mapper.skipped == 2 and mapper.processed == 1
    # odom (5.05, 5, 0) is 5 cm ahead of the first scan: in the map that is 5 cm along +y
    assert np.allclose(mapper.pose_at(np.array([5.05, 5.0, 0.0])), (1.0, 2.05, math.pi / 2), atol=1e-9)


def test_trajectory_holds_skipped_scans_and_follows_the_graph():
    mapper = LiveMapper(min_travel_m=0.1, min_turn_rad=0.1, start_pose=(1.0, 2.0, math.pi / 2))
    rng = np.random.default_rng(1)
    wall = np.stack([np.full(200, 3.0), np.linspace(-3, 3, 200)], axis=1) + rng.normal(0, 0.005, (200, 2))
    mapper.add_scan(0.0, np.array([5.0, 5.0, 0.0]), wall, np.zeros(2))
    mapper.add_scan(0.1, np.array([5.05, 5.0, 0.02]), wall, np.zeros(2))  # skipped
    mapper.note_skipped(0.15, np.array([5.07, 5.0, 0.0]))  # as the service records a gated scan
    assert mapper.add_scan(0.2, np.array([5.2, 5.0, 0.0]), wall - [0.2, 0.0], np.zeros(2))
    stamps, poses = mapper.trajectory()
    assert np.allclose(stamps, [0.0, 0.1, 0.15, 0.2])
    # skipped scans sit by odometry from the scan processed before them: +5 cm and +7 cm along map +y
    assert np.allclose(poses[1], (1.0, 2.05, math.pi / 2 + 0.02), atol=1e-9)
    assert np.allclose(poses[2], (1.0, 2.07, math.pi / 2), atol=1e-9)
    assert np.allclose(poses[3], mapper.pose)
    # they follow when the graph moves the scan they hang from
    moved = mapper.slam.graph.poses()
    moved[0] = (0.0, 0.0, 0.0)
    mapper.slam.graph.set_poses(moved)
    _, after = mapper.trajectory()
    assert np.allclose(after[1], (0.05, 0.0, 0.02), atol=1e-9) and np.allclose(after[2], (0.07, 0.0, 0.0), atol=1e-9)


def test_grow_to_cover_keeps_the_log_odds_in_place():
    grid = OccupancyGrid.covering(np.array([0.0, 0.0]), np.array([1.0, 1.0]), 0.1, margin_m=0.0)
    grid.log_odds[3, 4] = 2.5
    same = grow_to_cover(grid, np.array([[0.5, 0.5]]))
    assert same is grid
    bigger = grow_to_cover(grid, np.array([[-2.0, 0.5], [0.5, 3.0]]), margin_m=1.0)
    assert bigger.log_odds.shape[0] > grid.log_odds.shape[0] and bigger.log_odds.shape[1] > grid.log_odds.shape[1]
    x, y = grid.origin_xy_m + (np.array([4, 3]) + 0.5) * 0.1
    ix = int((x - bigger.origin_xy_m[0]) / 0.1)
    iy = int((y - bigger.origin_xy_m[1]) / 0.1)
    assert bigger.log_odds[iy, ix] == 2.5 and bigger.log_odds.sum() == 2.5
    assert bigger.origin_xy_m[0] <= -2.0 - 1.0 + 1e-9


def test_live_corridor_map_matches_the_world_and_incremental_render_equals_full():
    run = run_corridor(waypoints=[(0.0, 0.0, 0.0), (4.0, 0.1, 0.0), (4.0, 0.1, math.pi / 2), (4.0, 3.2, 0.0),
                                  (9.0, 3.2, 0.0)], render_every_scans=50)
    mapper = run.mapper
    assert mapper.skipped > mapper.processed > 50  # 4 cm per scan: about two in three are below the gates
    half = grid_to_map(mapper.render())
    assert mapper.full_renders == 1  # no loop closure on this route: every later keyframe was added in place
    full = grid_to_map(mapper.slam.render_map())
    same = occupied_f1(half.data >= 65, half.resolution, half.origin[:2], full.data >= 65, full.resolution,
                       full.origin[:2])
    assert same.f1 > 0.98  # the grids' cell boundaries differ by a fraction of a cell
    truth = run.world.occupancy_map()
    agreement = best_aligned_f1(half.data >= 65, half.resolution, half.origin[:2],
                                surface(truth.data == 100, truth.data == 0), truth.resolution, truth.origin[:2],
                                region=(-2.5, -2.0, 10.0, 5.5), built_free=half.data == 0)
    rms = float(np.sqrt(np.mean(run.errors_m ** 2)))
    print(f"\nsynthetic corridor to x = 9 m: F1 {agreement.f1:.3f} (P {agreement.precision:.3f}, "
          f"R {agreement.recall:.3f}), pose RMS {rms:.3f} m, CPU {1e3 * run.cpu_s_per_processed_scan:.1f} ms per "
          f"processed scan (max {1e3 * run.cpu_s_max:.0f} ms)")
    assert agreement.f1 >= 0.9
    assert rms < 0.1
