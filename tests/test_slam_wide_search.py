"""Loop closure after a long open loop: the graph's error exceeds the fixed correlative window, and a second search
widens with the pose uncertainty accumulated since the last accepted closure (``SlamConfig.loop_wide_sigmas``); a
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
    fixed, truth = _out_and_back(SlamConfig(), slip_m=3.0)
    _, fixed_poses = fixed.trajectory()
    assert np.hypot(*(fixed_poses[-1, :2] - truth[-1, :2])) > 2.0  # back in the room, still 3 m off: no closure
    wide, _ = _out_and_back(SlamConfig(loop_wide_sigmas=3.0), slip_m=3.0)
    _, poses = wide.trajectory()
    assert np.hypot(*(poses[-1, :2] - truth[-1, :2])) < 0.3
    big = [c for c in wide.loop_closures if c.correction > 2.0]
    assert big and len(wide.loop_closures) > len(fixed.loop_closures)
