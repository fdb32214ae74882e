"""SLAM core on synthetic data: matcher, pose graph, occupancy grid, error metric, CARMEN parsing."""

from __future__ import annotations

import numpy as np
import pytest

from services.common.se2 import between, compose, inverse, transform_points, wrap_angle
from services.localization.slam.evaluation import Relations, parse_relations, relative_pose_error
from services.localization.slam.likelihood import MultiResolutionGrid
from services.localization.slam.logs import parse_carmen
from services.localization.slam.map_files import read_trajectory, write_ros_map, write_trajectory
from services.localization.slam.matcher import correlative_search, refine, translation_sharpness
from services.localization.slam.occupancy import PGM_FREE, PGM_OCCUPIED, PGM_UNKNOWN, OccupancyGrid
from services.localization.slam.pose_graph import PoseGraph


def room_points(spacing_m: float = 0.02) -> np.ndarray:
    """Wall points of a 10 m x 8 m room with a 1 m x 2 m pillar and a short wall stub (asymmetric)."""
    segments = [((0, 0), (10, 0)), ((10, 0), (10, 8)), ((10, 8), (0, 8)), ((0, 8), (0, 0)),
                ((6, 3), (7, 3)), ((7, 3), (7, 5)), ((7, 5), (6, 5)), ((6, 5), (6, 3)), ((2, 8), (2, 6.5))]
    out = []
    for (x0, y0), (x1, y1) in segments:
        n = int(np.hypot(x1 - x0, y1 - y0) / spacing_m)
        s = np.linspace(0, 1, n, endpoint=False)
        out.append(np.stack([x0 + s * (x1 - x0), y0 + s * (y1 - y0)], axis=1))
    return np.concatenate(out)


def scan_from(pose: np.ndarray, world: np.ndarray, max_range_m: float = 8.0) -> np.ndarray:
    local = transform_points(inverse(pose), world)
    keep = np.hypot(local[:, 0], local[:, 1]) < max_range_m
    return local[keep][::3]


def test_se2_compose_inverse_between():
    a = np.array([1.0, 2.0, 0.7])
    b = np.array([-0.5, 0.3, -2.9])
    np.testing.assert_allclose(compose(a, inverse(a)), 0, atol=1e-12)
    np.testing.assert_allclose(compose(a, between(a, b)), b, atol=1e-12)
    assert abs(wrap_angle(3 * np.pi) - np.pi) < 1e-12


def test_refine_recovers_known_offset():
    world = room_points()
    grids = MultiResolutionGrid.from_points(world, 0.05, 3)
    truth = np.array([3.0, 4.0, 0.3])
    scan = scan_from(truth, world)
    result = refine(grids, scan, truth + np.array([0.15, -0.12, 0.06]))
    assert np.hypot(*(result.pose[:2] - truth[:2])) < 0.01
    assert abs(wrap_angle(result.pose[2] - truth[2])) < 0.005
    assert result.score > 0.8
    assert translation_sharpness(grids.levels[0], scan, result.pose) > 50.0
    # a corridor (two parallel walls) does not fix the position along it
    corridor = room_points()[:500]  # the wall y = 0, x in [0, 10)
    corridor = np.concatenate([corridor, corridor + [0.0, 2.0]])
    corridor_grids = MultiResolutionGrid.from_points(corridor, 0.05, 3)
    along = transform_points(inverse(np.array([5.0, 1.0, 0.0])), corridor[(corridor[:, 0] > 3) & (corridor[:, 0] < 7)])
    assert translation_sharpness(corridor_grids.levels[0], along, np.array([5.0, 1.0, 0.0])) < 1.0


def test_correlative_search_then_refine_recovers_large_offset():
    world = room_points()
    grids = MultiResolutionGrid.from_points(world, 0.05, 3)
    truth = np.array([4.0, 2.5, -1.0])
    scan = scan_from(truth, world)
    start = truth + np.array([0.7, -0.5, 0.25])
    assert refine(grids, scan, start).score < 0.9  # too far for local refinement alone
    candidates = correlative_search(grids.levels[-1], scan, start, window_xy_m=1.0, window_theta_rad=0.4,
                                    theta_step_rad=0.02)
    best = max((refine(grids, scan, pose) for _, pose in candidates), key=lambda r: r.score)
    assert np.hypot(*(best.pose[:2] - truth[:2])) < 0.01
    assert abs(wrap_angle(best.pose[2] - truth[2])) < 0.005


def test_pose_graph_closes_a_known_loop():
    # ground truth: a 4 m square driven counter-clockwise, a node every metre
    truth = []
    pose = np.zeros(3)
    for _side in range(4):
        for step in range(4):
            truth.append(pose.copy())
            turn = np.pi / 2 if step == 3 else 0.0
            pose = compose(pose, np.array([1.0, 0.0, turn]))
    truth = np.array(truth)
    graph = PoseGraph()
    drift = np.array([0.03, 0.01, 0.04])  # biased odometry: every step is off by this much
    info = np.diag([100.0, 100.0, 400.0])
    estimate = truth[0]
    graph.add_node(estimate)
    for k in range(1, len(truth)):
        z_true = between(truth[k - 1], truth[k])
        estimate = compose(estimate, z_true + drift)
        graph.add_node(estimate)
        graph.add_edge(k - 1, k, z_true, info)
    # the odometry chain is consistent with the (wrong) initial estimate except for the measurements
    graph.add_edge(len(truth) - 1, 0, between(truth[-1], truth[0]), info, robust_scale=5.0)
    before = np.abs(graph.poses()[:, :2] - truth[:, :2]).max()
    assert before > 0.5
    graph.optimize(30)
    np.testing.assert_allclose(graph.poses()[:, :2], truth[:, :2], atol=1e-6)
    np.testing.assert_allclose(wrap_angle(graph.poses()[:, 2] - truth[:, 2]), 0, atol=1e-6)
    assert graph.chi2() < 1e-8


def test_pose_graph_rejects_bad_edges():
    graph = PoseGraph()
    graph.add_node(np.zeros(3))
    with pytest.raises(ValueError, match="distinct existing nodes"):
        graph.add_edge(0, 1, np.zeros(3), np.eye(3))


def test_occupancy_grid_marks_wall_free_space_and_unknown(tmp_path):
    grid = OccupancyGrid.covering(np.array([-1.0, -2.0]), np.array([6.0, 2.0]), 0.1, margin_m=0.0)
    wall = np.stack([np.full(41, 4.0), np.linspace(-1.0, 1.0, 41)], axis=1)
    for _ in range(5):
        grid.insert_scan(np.zeros(3), np.zeros(2), wall)
    image = grid.trinary_image()[::-1]  # back to rows = increasing y

    def cell(x: float, y: float) -> int:
        return int(image[int((y - grid.origin_xy_m[1]) / 0.1), int((x - grid.origin_xy_m[0]) / 0.1)])

    assert cell(4.02, 0.02) == PGM_OCCUPIED
    assert cell(2.0, 0.0) == PGM_FREE
    assert cell(5.5, 0.0) == PGM_UNKNOWN
    assert cell(2.0, 1.9) == PGM_UNKNOWN
    yaml_path = write_ros_map(grid, tmp_path, "room")
    text = yaml_path.read_text()
    assert "image: room.pgm" in text and "resolution: 0.1" in text and "mode: trinary" in text
    raw = (tmp_path / "room.pgm").read_bytes()
    assert raw.startswith(b"P5\n")
    assert raw[-image.size:] == grid.trinary_image().tobytes()


def test_relative_pose_error_of_exact_and_perturbed_trajectories(tmp_path):
    stamps = np.arange(5.0)
    poses = np.array([[0, 0, 0], [1, 0, 0.1], [2, 0.2, 0.2], [3, 0.5, 0.3], [4, 0.9, 0.4]], float)
    rel = Relations(stamps[:-1], stamps[1:], between(poses[:-1], poses[1:]))
    exact = relative_pose_error(stamps, poses, rel)
    assert exact.translation_mean_m < 1e-12 and exact.rotation_mean_rad < 1e-12
    shifted = poses.copy()
    shifted[3:, 0] += 0.1  # one 10 cm jump between scans 2 and 3 (seen in the frame of scan 2)
    error = relative_pose_error(stamps, shifted, rel)
    assert error.translation_mean_m == pytest.approx(0.1 / 4)
    assert error.translation_max_m == pytest.approx(0.1)
    assert error.n_relations == 4 and error.n_missing == 0
    path = tmp_path / "t.txt"
    write_trajectory(path, stamps, poses)
    back_stamps, back_poses = read_trajectory(path)
    np.testing.assert_allclose(back_poses, poses, atol=1e-6)
    lines = ["1.0 2.0 0.5 0.0 0.0 0.0 0.0 0.1", "# comment", "", "2.0 9.5 1 2 0 0 0 -0.2"]
    parsed = parse_relations(lines)
    np.testing.assert_allclose(parsed.relative_pose, [[0.5, 0.0, 0.1], [1.0, 2.0, -0.2]])
    missing = relative_pose_error(stamps, poses, parsed)
    assert missing.n_missing == 1


def test_parse_carmen_flaser_and_robotlaser():
    lines = [
        "# comment line",
        "ODOM 1.0 2.0 0.0 0 0 0 100.0 host 0.1",
        "FLASER 5 1.00 2.00 81.91 3.00 4.00 10.0 20.0 0.5 11.0 21.0 0.6 1134864629.895182 b21 0.086295",
        "ROBOTLASER1 0 -1.5708 3.14159 0.785398 81.9 0.01 0 5 1.0 2.0 3.0 4.0 5.0 0 "
        "12.152968 22.128844 0.7 12.0 22.0 0.7 0.0 0.0 0.5 0.5 0.0 1134864630.000000 b21 0.2",
    ]
    log = parse_carmen(lines)
    assert len(log.scans) == 2
    first, second = log.scans
    assert first.stamp_s == pytest.approx(1134864629.895182)
    np.testing.assert_allclose(first.ranges_m, [1, 2, 81.91, 3, 4])
    np.testing.assert_allclose(first.angles_rad, [-np.pi / 2, -np.pi / 4, 0, np.pi / 4, np.pi / 2])
    np.testing.assert_allclose(first.odom_pose, [11.0, 21.0, 0.6])
    np.testing.assert_allclose(second.odom_pose, [12.0, 22.0, 0.7])
    assert second.max_range_m == pytest.approx(81.9)
    np.testing.assert_allclose(log.sensor_pose, [0.2, 0.0, 0.0], atol=1e-5)  # robot⁻¹ ⊕ laser of ROBOTLASER1
    with pytest.raises(ValueError, match="line 1: malformed FLASER"):
        parse_carmen(["FLASER 5 1.0 2.0"])


@pytest.mark.parametrize(("n_beams", "step_deg"), [(181, 1.0), (180, 1.0), (361, 0.5), (360, 0.5), (401, 0.25)])
def test_flaser_beam_spacing_follows_the_sick_modes(n_beams, step_deg):
    """CARMEN's FLASER: 180 and 360 beams are the 1° and 0.5° modes without their last beam (ending at +89° and
    +89.5°), not 180° spread over one beam fewer (which bends every wall by up to half a step at the edges)."""
    line = f"FLASER {n_beams} {' '.join(['2.0'] * n_beams)} 0 0 0 0 0 0 5.0 host 5.0"
    angles = parse_carmen([line]).scans[0].angles_rad
    np.testing.assert_allclose(np.diff(angles), np.radians(step_deg))
    assert angles[0] == pytest.approx(-np.pi / 2)
    assert angles[-1] == pytest.approx(-np.pi / 2 + (n_beams - 1) * np.radians(step_deg))
