"""Loop closure after a long open loop: the graph's error exceeds the fixed correlative window, and a second search
widens with the pose uncertainty relative to the candidate (``SlamConfig.loop_search_sigmas``); a
closure found so corrects more than a trusted one may and is accepted once another closure of the same revisit
confirms it."""

from __future__ import annotations

import numpy as np
import pytest

from services.common.se2 import between, compose
from services.localization.slam.mapper import GraphSlam, SlamConfig
from tests.test_slam_constraint import _scanner, _world

#: a room with an alcove, and a featureless corridor leaving it to the east (its far end beyond the laser's 20 m)
HALL = _world([[-4.0, -3.0, 4.0, 3.0], [1.0, 3.0, 2.0, 4.0], [4.0, -1.0, 75.0, 1.0]])
SLIP_AT = 70  # index of the odometry step that slips: 26.5 m down the corridor, the room out of the laser's reach


def _out_and_back(config: SlamConfig, slip_m: float) -> tuple[GraphSlam, np.ndarray]:
    """Through the room, 30 m down the corridor and back, 0.5 m per scan; in the corridor the odometry slips
    ``slip_m`` along it once, where no scan can see it, so the graph comes back to the room that far off."""
    scan = _scanner(HALL)
    truth: list[np.ndarray] = []
    pose = np.array([-2.0, -1.5, 0.0])
    for step, n in (((0.5, 0.0, 0.0), 7), ((0.0, 0.0, np.pi / 8), 4), ((0.5, 0.0, 0.0), 4),
                    ((0.0, 0.0, -np.pi / 8), 4), ((0.5, 0.0, 0.0), 60), ((0.0, 0.0, np.pi / 8), 8),
                    ((0.5, 0.0, 0.0), 64)):
        for _ in range(n):
            truth.append(pose.copy())
            pose = compose(pose, np.array(step))
    odom = [truth[0]]
    for k, (a, b) in enumerate(zip(truth[:-1], truth[1:], strict=True)):
        odom.append(compose(odom[-1], between(a, b) + (np.array([slip_m, 0.0, 0.0]) if k == SLIP_AT else 0.0)))
    slam = GraphSlam(config)
    for k, (t, o) in enumerate(zip(truth, odom, strict=True)):
        slam.add_scan(float(k), o, scan(t))
    slam.finish()
    return slam, np.array(truth)


@pytest.mark.timeout(600)  # two SLAM runs over 151 scans
def test_a_closure_beyond_the_fixed_window_is_found_by_the_widened_search():
    fixed, truth = _out_and_back(SlamConfig(loop_search_sigmas=0.0), slip_m=3.0)
    _, fixed_poses = fixed.trajectory()
    assert np.hypot(*(fixed_poses[-1, :2] - truth[-1, :2])) > 2.0  # back in the room, still 3 m off: no closure
    wide, _ = _out_and_back(SlamConfig(), slip_m=3.0)  # the default: 3 σ
    _, poses = wide.trajectory()
    assert np.hypot(*(poses[-1, :2] - truth[-1, :2])) < 0.3
    big = [c for c in wide.loop_closures if c.correction > 2.0]
    assert big and len(wide.loop_closures) > len(fixed.loop_closures)


def test_the_widened_search_leaves_the_path_just_driven_alone():
    """Down the corridor and never back: the keyframes 8 m behind are on the open loop being driven, as certain
    relative to the newest one as the few edges between them, so the widened gate (σ of Σ_jk, not of the whole drift
    since the start) never reaches them and no loop search runs. Searching them built their loop grids before the
    path had passed them, and those half neighbourhoods cost later closures (edmonton)."""
    scan = _scanner(HALL)
    slam = GraphSlam(SlamConfig(loop_search_sigmas=3.0))
    pose = np.array([-2.0, 0.0, 0.0])
    for k in range(130):  # 65 m
        slam.add_scan(float(k), pose, scan(pose))
        pose = compose(pose, np.array([0.5, 0.0, 0.0]))
    drift_sigma_m = float(np.sqrt(np.linalg.eigvalsh(slam.drift_covariance[:2, :2])[-1]))
    assert 4.0 + 3.0 * drift_sigma_m > SlamConfig().loop_min_travel_m  # the whole drift would reach 8 m back
    assert slam.loop_checks == 0 and not slam._loop_grids and not slam.closures
