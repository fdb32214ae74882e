"""Localization's per-direction uncertainty: the scan's information along a corridor, drift grown where the scans
do not pin the pose, and nav's goal checker refusing a pose localization cannot vouch for."""

from __future__ import annotations

import math

import numpy as np

from services.common.map_io import FREE, OCCUPIED, UNKNOWN, OccupancyMap
from services.common.se2 import compose, wrap_angle
from services.localization.amcl import Amcl, AmclParams, ParticleFilter, select_beams
from services.localization.realmap import MOUNT, GridLaser
from services.localization.uncertainty import PoseUncertainty, UncertaintyParams, scan_information
from tests.test_nav_navigator import drive, make

RES = 0.05


def long_hall(length_cells: int = 1200) -> OccupancyMap:
    """A hall 3 m wide and ``length_cells`` long (60 m), closed at both ends, starting at x = 1 m."""
    n = length_cells
    data = np.full((100, n + 40), UNKNOWN, dtype=np.int8)
    data[20:80, 20:n + 20] = FREE
    data[19, 19:n + 21] = OCCUPIED
    data[80, 19:n + 21] = OCCUPIED
    data[19:81, 19] = OCCUPIED
    data[19:81, n + 20] = OCCUPIED
    return OccupancyMap(data, RES, (0.0, 0.0, 0.0))


def information_at(grid: OccupancyMap, pose: tuple[float, float, float]) -> np.ndarray:
    params = AmclParams(random_seed=1)
    pf = ParticleFilter(grid, params)
    laser = GridLaser(grid, rng=np.random.default_rng(3))
    r = laser.scan(pose)
    b = select_beams(r, laser.angle_min, laser.angle_increment, laser.range_min, laser.range_max, params,
                     max_beams=r.size)
    return scan_information(pf.field.exact_distance_m(), grid.origin, grid.resolution, params.sigma_hit, pose,
                            b.ranges, b.bearings, MOUNT)


def test_scan_information_is_zero_along_a_hall_whose_ends_are_out_of_range_and_not_near_an_end():
    grid = long_hall()
    mid = information_at(grid, (31.0, 2.5, 0.0))  # ends 30 m away, laser range 20 m
    assert mid[0, 0] < 1e-6 * mid[1, 1]
    assert mid[1, 1] > 1e3  # the side walls pin y
    near_end = information_at(grid, (55.0, 2.5, 0.0))  # facing the east end, 5.9 m away
    assert near_end[0, 0] > 500.0


def test_drift_grows_only_along_the_direction_the_scans_do_not_pin():
    u = PoseUncertainty()
    u.reset(np.diag([0.01 ** 2, 0.01 ** 2, 0.005 ** 2]))
    pinned_y = np.diag([0.0, 1e5, 1e4])
    for _ in range(200):  # 20 m eastwards in 0.1 m steps, a scan after each
        u.predict(0.0, (0.1, 0.0, 0.0))
        u.update(pinned_y)
    expected = math.sqrt(UncertaintyParams().drift_xy_m2_per_m * 20.0)
    assert u.position_std_m() > 0.8 * expected
    assert abs(u.weakest_axis_rad()) < 0.05  # along x
    assert math.sqrt(u.covariance[1, 1]) < 0.01
    u.update(np.diag([1e5, 1e5, 1e4]))  # the end wall comes into view
    assert u.position_std_m() < 0.01


def test_heading_uncertainty_swings_a_step_across_it():
    u = PoseUncertainty(UncertaintyParams(drift_xy_m2_per_m=0.0))
    u.reset(np.diag([0.0, 0.0, 0.05 ** 2]))
    u.predict(0.0, (2.0, 0.0, 0.0))  # 2 m ahead with a 0.05 rad heading std: 0.1 m across
    assert math.isclose(math.sqrt(u.covariance[1, 1]), 0.1, rel_tol=0.05)
    assert math.sqrt(u.covariance[0, 0]) < 0.01


def test_filter_driven_along_a_featureless_hall_keeps_saying_it_does_not_know_x():
    """Odometry 4 % long along x, the hall's ends beyond the laser's (8 m) range: the estimate along x is dead
    reckoning; the tracked std along x covers its error and updates at rest do not shrink it, y stays pinned."""
    grid = long_hall(length_cells=800)
    params = AmclParams(random_seed=5, min_particles=300, max_particles=600)
    amcl = Amcl(grid, params)
    laser = GridLaser(grid, range_max=8.0, rng=np.random.default_rng(6))
    start = (14.0, 2.5, 0.0)
    amcl.set_initial_pose(start, np.diag([0.02 ** 2, 0.02 ** 2, 0.01 ** 2]))
    odom = (0.0, 0.0, 0.0)
    truth = start
    stds = []
    for k in range(110):  # 10 updates at rest, 12 m east at 0.15 m per scan, 20 updates at rest
        if 10 <= k < 90:
            truth = (truth[0] + 0.15, truth[1], truth[2])
            odom = compose(odom, (0.15 * 1.04, 0.0, 0.0))
        r = laser.scan(truth)
        beams = select_beams(r, laser.angle_min, laser.angle_increment, laser.range_min, laser.range_max, params)
        if k < 10 or k >= 90:
            amcl.request_nomotion_update()
        amcl.process(odom, beams, MOUNT, stamp=0.1 * k)
        stds.append(amcl.uncertainty.position_std_m())
    assert amcl.state == "tracking"
    assert amcl.estimate is not None
    err_x = amcl.estimate.pose[0] - truth[0]
    assert stds[9] < 0.025 and stds[-1] > 0.08, (stds[9], stds[-1])
    assert stds[-1] > abs(err_x) / 2, (stds[-1], err_x)
    assert stds[-1] >= stds[89] - 1e-9  # the view at rest pins nothing more along x
    assert abs(wrap_angle(amcl.uncertainty.weakest_axis_rad())) < 0.1
    y_std = math.sqrt(amcl.uncertainty.covariance[1, 1])
    assert y_std < 0.02, y_std


def test_goal_checker_fails_a_goal_localization_cannot_vouch_for():
    nav, sim = make((0.0, 0.0, 0.0))
    nav.loc_position_std_m, nav.loc_weakest_axis_rad = 0.08, 0.0
    ok, gid, _ = nav.start_goal(0.0, (3.0, 0.1, 1.57))
    assert ok
    drive(nav, sim, 120.0)
    assert nav.state == "failed"
    assert "cannot vouch for the position: std 0.080 m along 0 deg" in nav.error, nav.error
    assert [e[:2] for e in nav.take_finished()] == [(gid, "failed")]


def test_goal_checker_waits_for_localization_to_vouch_then_succeeds():
    nav, sim = make((0.0, 0.0, 0.0))
    nav.loc_heading_std_rad = 0.04  # over 0.05 rad / 2
    ok, gid, _ = nav.start_goal(0.0, (3.0, 0.1, 1.57))
    assert ok
    drive(nav, sim, 120.0, stop_when=lambda: nav.goal is not None and nav.goal.vouch_wait_since is not None)
    assert nav.state not in ("succeeded", "failed")
    nav.loc_heading_std_rad = 0.01  # an update at rest pinned it
    drive(nav, sim, 10.0)
    assert nav.state == "succeeded", nav.error
    finished = nav.take_finished()
    assert finished[0][:2] == (gid, "succeeded") and "localization std 0.0000 m" in finished[0][2]
    assert "vouched after" in finished[0][2]
