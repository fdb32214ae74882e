"""What makes a replayed localization repeat the live one: scans wait for the odometry of their stamp whatever the
order the two streams arrive in (``scan_queue.py``), and a seeded filter restarts its generator at each
initialisation, so that its state after one depends only on the inputs since."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from services.common.world import World
from services.localization.amcl import Amcl, AmclParams, select_beams
from services.localization.scan_queue import ScanQueue
from services.localization.synthetic import Laser

MOUNT = (0.45, 0.0, 0.0)


@dataclass
class Msg:
    stamp: float


def test_scans_wait_for_the_odometry_of_their_stamp_in_order() -> None:
    q: ScanQueue[Msg] = ScanQueue(3)
    a, b, c = Msg(1.00), Msg(1.04), Msg(1.08)
    assert q.push(a) == [] and q.push(b) == []
    assert q.ready(0.99) == [] and q.ready(None) == []
    assert q.ready(1.02) == [a]  # the odom passed a's stamp only
    assert q.push(c) == [] and q.ready(1.10) == [b, c] and len(q) == 0


def test_when_the_odometry_stalls_the_oldest_scans_leave_the_queue() -> None:
    q: ScanQueue[Msg] = ScanQueue(2)
    scans = [Msg(1.0 + 0.04 * i) for i in range(4)]
    assert q.push(scans[0]) == [] and q.push(scans[1]) == []
    assert q.push(scans[2]) == [scans[0]] and q.push(scans[3]) == [scans[1]]
    q.clear()
    assert len(q) == 0 and q.ready(9.0) == []
    assert ScanQueue[Msg](0).push(scans[0]) == [scans[0]]
    with pytest.raises(ValueError, match="max_waiting"):
        ScanQueue[Msg](-1)


def test_arrival_order_does_not_change_which_odometry_a_scan_gets() -> None:
    """Live the scan may come before the odom that passes it, in a replay after it: the same scans leave the queue
    for the same odometry either way."""
    def run(order: list[tuple[str, float]]) -> list[tuple[float, float]]:
        q: ScanQueue[Msg] = ScanQueue(10)
        latest = None
        placed = []
        for kind, stamp in order:
            if kind == "odom":
                latest = stamp
                placed += [(s.stamp, latest) for s in q.ready(latest)]
            else:
                q.push(Msg(stamp))
                placed += [(s.stamp, latest) for s in q.ready(latest)]
        return [s for s, _ in placed]

    live = [("odom", 1.00), ("scan", 1.03), ("scan", 1.07), ("odom", 1.02), ("odom", 1.04), ("odom", 1.08)]
    replay = [("odom", 1.00), ("odom", 1.02), ("scan", 1.03), ("odom", 1.04), ("scan", 1.07), ("odom", 1.08)]
    assert run(live) == run(replay) == [1.03, 1.07]


def room() -> tuple[World, Laser]:
    world = World.from_rectangles("room", 0.05, [-0.5, -0.5, 8.5, 4.5], [[0.0, 0.0, 8.0, 4.0]], [[5.0, 1.0, 5.5, 2.0]])
    return world, Laser(world)


def test_a_seeded_filter_repeats_itself_from_each_initialisation_whatever_came_before() -> None:
    world, laser = room()
    grid = world.occupancy_map()
    params = AmclParams(random_seed=11, update_min_d=0.05)

    route = [(2.0 + 0.06 * k, 2.0, 0.01 * k) for k in range(12)]
    # the recorded scans (the simulated laser is noisy: each scan is drawn once, as a bag holds it)
    scans = [select_beams(laser.scan(pose, MOUNT), laser.angle_min, laser.angle_increment, 0.05, 20.0, params)
             for pose in route]
    live, replayed = Amcl(grid, params), Amcl(grid, params)
    live.set_initial_pose((3.0, 2.5, 0.2))
    for k, pose in enumerate(route[:6]):  # the live filter ran on scans the recording does not hold
        live.process(pose, scans[-1 - k], MOUNT, stamp=0.04 * k)
    cov = np.diag([0.01, 0.01, 0.01])
    for amcl in (live, replayed):
        amcl.set_initial_pose(route[0], cov)
        for k, pose in enumerate(route):
            amcl.process(pose, scans[k], MOUNT, stamp=1.0 + 0.04 * k)
    assert np.array_equal(live.pf.poses[:live.pf.n], replayed.pf.poses[:replayed.pf.n])
    assert live.estimate is not None and replayed.estimate is not None
    assert live.estimate.pose == replayed.estimate.pose and live.map_odom == replayed.map_odom
    # an unseeded filter draws afresh
    free = AmclParams(update_min_d=0.05)
    one, two = Amcl(grid, free), Amcl(grid, free)
    for amcl in (one, two):
        amcl.set_initial_pose(route[0], cov)
    assert not np.array_equal(one.pf.poses[:one.pf.n], two.pf.poses[:two.pf.n])
