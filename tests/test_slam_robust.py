"""Robustness of the SLAM: laser mount handling, odometry corruption, loop-closure verification, the bench slice."""

from __future__ import annotations

import math

import msgspec
import numpy as np
import pytest

from services.common.se2 import between, compose
from services.localization.slam.evaluation import aligned_trajectory_error, edge_bias, false_closures, scan_poses
from services.localization.slam.logs import parse_carmen, read_log, with_mount
from services.localization.slam.mapper import GraphSlam, LoopClosure
from services.localization.slam.odometry_noise import OdometryNoise, corrupt_poses
from services.localization.slam.offline import run_slam


@pytest.fixture
def logs_dir(shared_dir):
    path = shared_dir / "data" / "logs"
    if not (path / "mit-csail.clf").is_file():
        pytest.skip(f"benchmark logs not found in {path}")
    return path


def test_carmen_front_laser_offset_and_unusable_stamps():
    scan = " ".join(["1.0"] * 5)
    lines = ["PARAM robot_frontlaser_offset 0.25 0 host 0",
             f"FLASER 5 {scan} 0 0 0 0 0 0 1.13486e+09 pippo 1.13486e+09",
             f"FLASER 5 {scan} 1 0 0 1 0 0 1.13486e+09 pippo 1.13486e+09",
             f"FLASER 5 {scan} 2 0 0 2 0 0 1.13486e+09 pippo 1.13486e+09"]
    log = parse_carmen(lines)
    np.testing.assert_allclose(log.sensor_pose, [0.25, 0.0, 0.0])
    assert not log.stamps_from_log  # truncated stamps: the scan index stands in
    assert [s.stamp_s for s in log.scans] == [0.0, 1.0, 2.0]
    np.testing.assert_allclose([s.odom_pose[0] for s in log.scans], [0, 1, 2])  # file order kept
    bad = "ROBOTLASER1 0 -1.5708 3.14159 1.5708 81.9 0.01 0 3 1 1 1 0 50 0 0 0 0 0 0 0 0 0 0 0 5.0 h 5.0"
    with pytest.raises(ValueError, match="not a mount offset"):
        parse_carmen([bad])


def test_raw_carmen_laser_records_take_the_odometry_at_their_stamp():
    """A log of RAWLASER1 and ODOM records only: each scan gets the odometry interpolated at its stamp; a scan
    outside the odometry's time is left out, and scans with no ODOM record at all are an error naming both."""
    scan = "RAWLASER1 0 -1.5708 3.14159 0.0174533 81.9 0.01 0 5 1 2 3 4 5 0 {t} host {t}"
    lines = ["ODOM 0 0 0 0.5 0 0 100.0 host 100.0", scan.format(t=99.5),  # before the first ODOM: left out
             scan.format(t=100.25), "ODOM 1 0 0.4 0.5 0 0 101.0 host 101.0", scan.format(t=100.75),
             "ODOM 1 2 0.4 0.5 0 0 102.0 host 102.0", scan.format(t=101.5)]
    log = parse_carmen(lines)
    assert [s.stamp_s for s in log.scans] == [100.25, 100.75, 101.5]
    np.testing.assert_allclose([s.odom_pose for s in log.scans], [[0.25, 0, 0.1], [0.75, 0, 0.3], [1, 1, 0.4]])
    np.testing.assert_allclose(log.scans[0].angles_rad, -1.5708 + np.arange(5) * 3.14159 / 4)
    np.testing.assert_allclose(log.scans[0].ranges_m, [1, 2, 3, 4, 5])
    with pytest.raises(ValueError, match="3 RAWLASER1 scans but no ODOM record"):
        parse_carmen([scan.format(t=1.0), scan.format(t=2.0), scan.format(t=3.0)])
    # truncated stamps order nothing: each scan takes the ODOM line read before it (the first one at the start)
    truncated = [scan.format(t=1.1e9), "ODOM 0 0 0 0 0 0 1.1e9 host 0", scan.format(t=1.1e9),
                 "ODOM 1 0 0.4 0 0 0 1.1e9 host 0", "ODOM 2 0 0.5 0 0 0 1.1e9 host 0", scan.format(t=1.1e9)]
    log = parse_carmen(truncated)
    assert not log.stamps_from_log
    np.testing.assert_allclose([s.odom_pose for s in log.scans], [[0, 0, 0], [0, 0, 0], [2, 0, 0.5]])


def test_a_log_with_each_scan_in_several_record_kinds_gives_each_scan_once():
    """A CARMEN logger may write each front-laser scan as ROBOTLASER1, FLASER and RAWLASER1: the scan is read
    once, from ROBOTLASER1 (its own mount and range limit); a FLASER line of another moment is a scan of its own."""
    robot = ("ROBOTLASER1 0 -1.5708 3.14159 0.785398 30.0 0.01 0 5 1 2 3 4 5 0 "
             "{x1} 0 0 {x} 0 0 0 0 0 0 0 {t} host {t}")
    flaser = "FLASER 5 1 2 3 4 5 {x1} 0 0 {x} 0 0 {t} host {t}"
    raw = "RAWLASER1 0 -1.5708 3.14159 0.785398 30.0 0.01 0 5 1 2 3 4 5 0 {t} host {t}"
    lines = []
    for k in range(4):
        values = {"x": float(k), "x1": k + 0.2, "t": 10.0 + k}
        lines += [f"ODOM {k} 0 0 0 0 0 {10.0 + k} host 0", robot.format(**values), flaser.format(**values),
                  raw.format(t=10.0 + k)]
    log = parse_carmen(lines)
    assert [s.stamp_s for s in log.scans] == [10.0, 11.0, 12.0, 13.0]
    assert all(s.max_range_m == 30.0 for s in log.scans)
    np.testing.assert_allclose(log.sensor_pose, [0.2, 0.0, 0.0])
    flaser_only = parse_carmen([line for line in lines if line.startswith("FLASER")])
    assert len(flaser_only.scans) == 4
    between_them = parse_carmen(lines[:4] + [flaser.format(x=1.5, x1=1.7, t=10.5)] + lines[4:])
    assert [s.stamp_s for s in between_them.scans] == [10.0, 10.5, 11.0, 12.0, 13.0]


def test_a_real_log_as_raw_records_reads_as_its_flaser_lines(logs_dir):
    """MIT CSAIL's FLASER lines rewritten as the raw records a CARMEN logger also writes (RAWLASER1 with the
    scan, ODOM with the odometry, half a scan interval apart): the same scans at the same odometry."""
    flaser = [line for line in (logs_dir / "mit-csail.clf").read_text().splitlines() if line.startswith("FLASER")]
    flaser = flaser[:400]
    raw: list[str] = []
    previous = None
    for line in flaser:
        f = line.split()
        n = int(f[1])
        odom, stamp = f[5 + n:8 + n], float(f[8 + n])
        if previous is not None:  # an ODOM record between two scans, on the straight line between their poses
            (x0, y0, t0), s0 = previous
            mid = [(float(a) + float(b)) / 2 for a, b in zip((x0, y0), odom[:2], strict=True)]
            turn = math.remainder(float(odom[2]) - float(t0), 2 * math.pi)
            raw.append(f"ODOM {mid[0]} {mid[1]} {float(t0) + turn / 2} 0 0 0 {(s0 + stamp) / 2} host 0")
        raw.append(f"ODOM {' '.join(odom)} 0 0 0 {stamp} host 0")
        raw.append(f"RAWLASER1 0 {-math.pi / 2} {math.pi} {math.pi / (n - 1)} 81.91 0.01 0 {n} "
                   f"{' '.join(f[2:2 + n])} 0 {stamp} host 0")
        previous = (odom, stamp)
    original, rewritten = parse_carmen(flaser), parse_carmen(raw)
    assert len(rewritten.scans) == len(original.scans) == 400
    for a, b in zip(original.scans, rewritten.scans, strict=True):
        assert a.stamp_s == b.stamp_s
        np.testing.assert_allclose(b.odom_pose, a.odom_pose, atol=1e-9)
        np.testing.assert_allclose(b.angles_rad, a.angles_rad, atol=1e-9)
        np.testing.assert_array_equal(b.ranges_m, a.ranges_m)


def test_odometry_corruption_is_seeded_and_as_documented():
    # 100 m straight along x in 0.1 m steps
    truth = np.stack([np.arange(1001) * 0.1, np.zeros(1001), np.zeros(1001)], axis=1)
    drift_only = OdometryNoise(seed=3, scale_error=0.05, drift_rad_per_m=math.radians(2.0))
    odom, jumps = corrupt_poses(truth, drift_only)
    assert jumps == 0
    steps = between(odom[:-1], odom[1:])
    assert abs(np.hypot(steps[:, 0], steps[:, 1]).sum() / 100.0 - 1.0) == pytest.approx(0.05)  # wheel scale ±5 %
    np.testing.assert_allclose(np.abs(steps[:, 2]), math.radians(2.0) * 0.1)  # 2°/m, one sign per run
    degraded = OdometryNoise.degraded(seed=7)
    a, jumps_a = corrupt_poses(truth, degraded)
    b, _ = corrupt_poses(truth, degraded)
    np.testing.assert_array_equal(a, b)
    assert jumps_a >= 1  # about one per 50 m
    c, _ = corrupt_poses(truth, OdometryNoise.degraded(seed=8))
    assert np.abs(a - c).max() > 0.1
    assert "2°/m" in degraded.describe() and "±5 %" in degraded.describe()


def test_turning_odometry_adds_rotation_errors_and_leaves_the_other_terms_as_they_were():
    # 20 m straight, then ten turns on the spot (2π each, 0.1 rad steps), then 20 m on
    straight = np.stack([np.arange(201) * 0.1, np.zeros(201), np.zeros(201)], axis=1)
    spin = np.stack([np.full(629, 20.0), np.zeros(629), np.arange(1, 630) * 0.1], axis=1)
    on = np.stack([20.0 + np.cos(62.9) * np.arange(1, 201) * 0.1, np.sin(62.9) * np.arange(1, 201) * 0.1,
                   np.full(200, 62.9)], axis=1)
    truth = np.concatenate([straight, spin, on])
    degraded, turning = OdometryNoise.degraded(seed=5), OdometryNoise.turning(seed=5)
    a, jumps_a = corrupt_poses(truth, degraded)
    b, jumps_b = corrupt_poses(truth, turning)
    without_turns, _ = corrupt_poses(truth, msgspec.structs.replace(turning, rot_scale_error=0.0,
                                                                    noise_theta_per_rad=0.0))
    np.testing.assert_array_equal(a, without_turns)  # the same draws for every other term
    assert jumps_a == jumps_b
    # degraded odometry gets the spin right (it grows with distance only); turning odometry is off by about 8 %
    # of the 62.9 rad turned, with the noise's sqrt(629)·0.1·0.05 = 0.13 rad on top
    def spin_error(poses: np.ndarray) -> float:  # the turn summed over the spin's increments, less the true 62.9 rad
        return float(between(poses[200:829], poses[201:830])[:, 2].sum() - 62.9)

    assert abs(spin_error(a)) < 1e-9
    assert abs(abs(spin_error(b)) - 0.08 * 62.9) < 0.5
    assert "turns scaled ±8 %" in turning.describe() and "turns" not in degraded.describe()


def test_aligned_trajectory_error_ignores_a_rigid_motion():
    rng = np.random.default_rng(0)
    reference = np.cumsum(rng.normal(0, 0.3, (200, 3)), axis=0)
    moved = compose(np.broadcast_to([5.0, -3.0, 1.2], reference.shape), reference)
    assert aligned_trajectory_error(moved, reference).rms_m < 1e-9
    noisy = moved + np.c_[rng.normal(0, 0.05, (200, 2)), np.zeros(200)]
    assert aligned_trajectory_error(noisy, reference).rms_m == pytest.approx(0.05 * math.sqrt(2), rel=0.2)
    measured = np.array([between(reference[3], reference[150]), [0.5, 0.0, 0.0]])
    assert false_closures(np.array([3, 3]), np.array([150, 150]), measured, reference).tolist() == [False, True]


def _chain_graph(n: int) -> GraphSlam:
    """A GraphSlam whose graph is a square loop of n keyframes 1 m apart with exact sequential edges."""
    slam = GraphSlam()
    side = n // 4
    poses = []
    pose = np.zeros(3)
    for k in range(n):
        poses.append(pose.copy())
        step = np.array([1.0, 0.0, math.pi / 2 if (k + 1) % side == 0 else 0.0])
        pose = compose(pose, step)
    for k, p in enumerate(poses):
        slam.graph.add_node(p)
        slam._keyframes.append(type("K", (), {"travel_m": float(k)})())
        slam._drift_covariances.append(np.zeros((3, 3)))  # the bookkeeping _add_keyframe keeps per keyframe
        slam._drift_xy_m.append(np.asarray(p[:2], float))
        slam._drift_anchors.append(0)
        if k:
            slam.graph.add_edge(k - 1, k, between(poses[k - 1], p), slam._sequential_info)
    return slam


def test_false_loop_closure_is_rejected_and_true_ones_kept():
    slam = _chain_graph(40)
    poses = slam.graph.poses()
    true_a = LoopClosure(0, 38, between(poses[0], poses[38]), 0.0)
    true_b = LoopClosure(1, 39, between(poses[1], poses[39]), 0.0)
    false = LoopClosure(5, 36, compose(between(poses[5], poses[36]), np.array([1.5, 0.8, 0.3])), 1.9)
    slam.closures += [true_a, true_b, false]
    assert slam._consistent(true_a, true_b, poses)
    assert not slam._consistent(true_a, false, poses)
    for closure in (true_a, true_b, false):
        slam._accept(closure)
    slam.optimize()
    assert [c.state for c in (true_a, true_b, false)] == ["accepted", "accepted", "rejected"]
    assert slam.rejected_closures == [false] and false.reason == "contradicts the graph"
    error = between(poses, slam.graph.poses())  # the false edge no longer bends the graph
    assert np.abs(error[:, :2]).max() < 1e-3 and np.abs(error[:, 2]).max() < 1e-3


def test_pending_closure_needs_a_consistent_partner():
    slam = _chain_graph(40)
    poses = slam.graph.poses()
    offset = np.array([0.6, 0.0, 0.0])  # both see the same large correction: the graph drifted, not the matcher
    a = LoopClosure(0, 36, compose(between(poses[0], poses[36]), offset), 0.6)
    b = LoopClosure(1, 37, compose(between(poses[1], poses[37]), offset), 0.6)
    lonely = LoopClosure(10, 30, compose(between(poses[10], poses[30]), np.array([0.0, 0.9, 0.2])), 1.1)
    slam.closures += [lonely]
    slam._check_pending(30)
    assert lonely.state == "pending"
    slam.closures += [a, b]
    slam._check_pending(37)
    assert a.state == b.state == "accepted"
    slam._check_pending(30 + slam.config.loop_consistency_keyframes + 1)
    assert lonely.state == "rejected" and lonely.reason == "no consistent closure"


def test_closures_that_disagree_by_more_than_their_own_error_do_not_confirm_each_other():
    """Two closures of one revisit (1 m of path apart) that disagree by 0.25 m: each is stated to 0.03 m, so their
    cycle should close to about 0.04 m; they are no evidence for each other (two look-alike matches, each 0.3-0.5 m
    off, confirmed each other at the old 0.3 m tolerance). 0.1 m apart they agree."""
    slam = _chain_graph(40)
    poses = slam.graph.poses()
    a = LoopClosure(0, 36, compose(between(poses[0], poses[36]), np.array([0.4, 0.0, 0.0])), 0.4)
    far = LoopClosure(0, 37, compose(between(poses[0], poses[37]), np.array([0.4, 0.25, 0.0])), 0.5)
    near = LoopClosure(0, 37, compose(between(poses[0], poses[37]), np.array([0.4, 0.1, 0.0])), 0.4)
    assert not slam._consistent(a, far, poses)
    assert slam._consistent(a, near, poses)


def test_a_small_correction_is_trusted_only_where_the_graph_is_sure():
    """A closure that asks the graph for 0.2 m is accepted at once when k is known to 0.1 m relative to j; after a
    long open loop (σ_xy(Σ_jk) = 2 m) the same small correction is no evidence (a look-alike place can agree with a
    drifted graph) and it must be confirmed like a large one."""
    slam = _chain_graph(40)
    k, j = 39, 0
    assert slam._trusted(j, k, 0.2, 0.01)  # Σ_k = 0: the graph is sure
    assert not slam._trusted(j, k, 0.4, 0.01) and not slam._trusted(j, k, 0.2, 0.08)  # too large a correction
    slam.drift_covariance = np.diag([0.1**2, 0.1**2, 1e-4])
    assert slam._trusted(j, k, 0.2, 0.01)
    slam.drift_covariance = np.diag([2.0**2, 0.5**2, 1e-3])
    assert not slam._trusted(j, k, 0.2, 0.01)
    # relative to a keyframe on the same chain since the anchor, only the edges between them count
    slam._drift_covariances[k - 2] = slam.drift_covariance - np.diag([0.05**2, 0.05**2, 0.0])
    assert slam._trusted(k - 2, k, 0.2, 0.01)
    slam.config.loop_trusted_sigma_xy_m = 3.0
    assert slam._trusted(j, k, 0.2, 0.01)


def test_closures_of_different_revisits_do_not_confirm_each_other():
    """Two wrong closures to places far apart along the path agree within the tolerance a long cycle allows
    (0.15 m + 0.01 m per m of path: 0.39 m over 24 m) but are no evidence for each other: only a closure of the same
    revisit, within ``loop_consistency_max_path_m`` of path, can confirm one."""
    slam = _chain_graph(80)
    poses = slam.graph.poses()
    a = LoopClosure(0, 60, compose(between(poses[0], poses[60]), np.array([0.3, 0.2, 0.0])), 0.5)
    b = LoopClosure(12, 72, compose(between(poses[12], poses[72]), np.array([0.45, 0.35, 0.0])), 0.6)
    assert slam._path_length(a.to, b.to) + slam._path_length(a.from_, b.from_) == pytest.approx(24.0)
    assert not slam._consistent(a, b, poses)
    slam.config.loop_consistency_max_path_m = 30.0
    assert slam._consistent(a, b, poses)  # what the long cycle's tolerance alone would have let through


@pytest.mark.timeout(900)  # two SLAM runs over 150 scans: ~8 s of CPU
def test_mount_offset_does_not_change_the_result(logs_dir):
    """The same scans re-expressed for a laser 0.25 m ahead and 0.05 m left of the robot frame, and the
    trajectory of the laser (what the relations measure) stays the same up to matcher noise (the robot frame moves,
    so keyframes are picked at slightly different scans: ~1 cm RMS); a misapplied 0.25 m mount would show as
    decimetres."""
    log = read_log(logs_dir / "mit-csail.clf")
    log.scans = log.scans[:150]
    shifted = with_mount(log, np.array([0.25, 0.05, 0.0]))
    laser_before = scan_poses(np.array([s.odom_pose for s in log.scans]), log.sensor_pose)
    laser_after = scan_poses(np.array([s.odom_pose for s in shifted.scans]), shifted.sensor_pose)
    np.testing.assert_allclose(laser_after, laser_before, atol=1e-9)
    runs = [run_slam(x) for x in (log, shifted)]
    lasers = [scan_poses(r.slam.trajectory()[1], x.sensor_pose) for r, x in zip(runs, (log, shifted), strict=True)]
    rel = [between(p[0], p) for p in lasers]  # both relative to the first scan's laser pose
    d = np.hypot(*(rel[0][:, :2] - rel[1][:, :2]).T)
    assert d.max() < 0.10 and np.sqrt(np.mean(d**2)) < 0.03, (d.max(), np.sqrt(np.mean(d**2)))
    grids = [r.slam.render_map() for r in runs]
    occupied = [(g.probability() > 0.65).sum() for g in grids]
    assert abs(occupied[0] - occupied[1]) < 0.05 * occupied[0]


def test_a_reference_in_another_metric_shows_as_scale_not_as_scaled_error():
    """A map uniformly 0.4 % smaller than its reference: the rigid error grows with the extent, the Sim(2) fit
    recovers the scale and leaves nothing."""
    rng = np.random.default_rng(4)
    reference = np.column_stack([rng.uniform(0, 200, 500), rng.uniform(0, 60, 500), rng.uniform(-3, 3, 500)])
    ours = reference.copy()
    ours[:, :2] = (reference[:, :2] - 50.0) / 1.004  # same shape, smaller, elsewhere
    ours = compose(np.broadcast_to(np.array([3.0, -1.0, 0.4]), ours.shape), ours)
    error = aligned_trajectory_error(ours, reference)
    assert error.rms_m > 0.15
    assert error.scale == pytest.approx(1.004, abs=1e-9)
    assert error.scaled_rms_m < 1e-9
    assert aligned_trajectory_error(reference, reference).scale == pytest.approx(1.0)


def test_edge_bias_measures_a_uniform_shortening_and_a_steady_turn_not_zero_mean_noise():
    rng = np.random.default_rng(5)
    headings = np.cumsum(rng.uniform(-0.4, 0.4, 200))
    steps = np.column_stack([np.full(200, 0.8), np.zeros(200), np.diff(headings, prepend=0.0)])
    steps[50] = [0.0, 0.0, 1.2]  # a turn on the spot: no direction to measure along, left out
    reference = np.zeros((201, 3))
    for k, step in enumerate(steps):
        reference[k + 1] = compose(reference[k], step)
    true_steps = between(reference[:-1], reference[1:])
    biased = true_steps * np.array([0.997, 0.997, 1.0]) + np.array([0.0, 0.0, 0.001])
    bias = edge_bias(reference[:-1], reference[1:], biased)
    assert bias.n_edges == 199 and bias.path_m == pytest.approx(199 * 0.8)
    assert bias.along_pct == pytest.approx(-0.3, abs=1e-9)
    assert bias.heading_deg_per_100m == pytest.approx(100 * math.degrees(0.001 * 199) / (199 * 0.8), rel=1e-9)
    turns = np.abs(true_steps[:, 2]) > 0.05
    expected = 100 * np.sum(0.001 * np.sign(true_steps[turns, 2])) / np.sum(np.abs(true_steps[turns, 2]))
    assert bias.turn_pct == pytest.approx(expected, rel=1e-9)
    under_turned = true_steps * np.array([1.0, 1.0, 0.98])  # every turn 2 % short, left and right alike
    assert edge_bias(reference[:-1], reference[1:], under_turned).turn_pct == pytest.approx(-2.0, rel=1e-9)
    assert abs(edge_bias(reference[:-1], reference[1:], under_turned).heading_deg_per_100m) < \
        100 * math.degrees(0.02 * np.abs(true_steps[:, 2]).sum()) / (199 * 0.8)  # partly cancelled in the plain sum
    noisy = true_steps + rng.normal(0.0, [0.01, 0.01, 0.003], true_steps.shape)
    unbiased = edge_bias(reference[:-1], reference[1:], noisy)
    assert abs(unbiased.along_pct) < 0.3 and abs(unbiased.heading_deg_per_100m) < 5.0
    with pytest.raises(ValueError, match="measured edges"):
        edge_bias(reference[:-1], reference[1:], biased[:-1])
    assert math.isnan(edge_bias(reference[:2], reference[1:3], true_steps[:2] * [1.0, 1.0, 0.0],
                                min_turn_rad=10.0).turn_pct)


def test_suspect_reference_poses_finds_the_poses_their_own_scans_disagree_with():
    """A reference trajectory with one pose turned 0.1 rad and one shifted 0.25 m: those two, and no neighbour
    that shares scans with them, are the poses a closure cannot be judged by."""
    from services.common.world import World
    from services.localization.slam.mapper import scan_to_points
    from services.localization.slam.reference_check import suspect_reference_poses
    from services.localization.synthetic import Laser, route

    world = World.load_builtin("corridor")
    laser = Laser(world, beams=361, fov_rad=math.pi, range_max=20.0, rng=np.random.default_rng(1))
    truth = np.array(list(route([(0.0, 0.0, 0.0), (4.0, 0.1, 0.0), (4.0, 0.1, math.pi / 2), (4.0, 3.2, math.pi / 2),
                                 (4.0, 3.2, 0.0), (12.0, 3.2, 0.0)], step_m=0.5, step_rad=0.3)))
    mount = (0.2, 0.0, 0.0)
    clouds = [scan_to_points(laser.scan(tuple(p), mount), laser.angles, np.array(mount), min_range_m=0.05,
                             max_range_m=20.0) for p in truth]
    reference = truth.copy()
    reference[9, 2] += 0.1
    reference[20, :2] += [0.25 * math.cos(reference[20, 2]), 0.25 * math.sin(reference[20, 2])]
    assert suspect_reference_poses(lambda i: clouds[i], truth, range(len(truth))) == set()
    assert suspect_reference_poses(lambda i: clouds[i], reference, range(len(truth))) == {9, 20}
    assert suspect_reference_poses(lambda i: clouds[i], reference, [3, 20]) == {20}


def test_loop_neighbourhoods_are_rebuilt_after_the_graph_moves():
    """A keyframe's cached loop neighbourhood holds its neighbours where the graph had them: after an optimisation
    has moved them (a closure bent the chain), a later loop search must see them where they are now."""
    slam = _chain_graph(40)
    for keyframe in slam._keyframes:
        keyframe.points = np.array([[1.0, 0.5], [1.0, -0.5], [2.0, 0.0]])
    first = slam._loop_grid(5, 20)
    assert slam._loop_grid(5, 20) is first  # cached while nothing moved
    poses = slam.graph.poses()
    slam._accept(LoopClosure(0, 39, compose(between(poses[0], poses[39]), np.array([0.3, 0.0, 0.05])), 0.35))
    slam.optimize()
    moved = between(poses[5], poses[10]) - between(slam.graph.poses()[5], slam.graph.poses()[10])
    assert np.abs(moved).max() > 1e-3  # the neighbourhood of 5 changed shape
    rebuilt = slam._loop_grid(5, 20)
    assert rebuilt is not first
    assert not np.array_equal(rebuilt.levels[0].field, first.levels[0].field) or \
        not np.allclose(rebuilt.levels[0].origin_xy_m, first.levels[0].origin_xy_m)
