"""nav's pose tracking and controller cycle as plain code (services/nav/pose_tracker.py, services/nav/cycle.py)."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest

from proto import messages as m
from services.common.robot import RobotSpec
from services.common.se2 import wrap_angle
from services.nav.config import NavConfig
from services.nav.cycle import NavCycle
from services.nav.navigator import Navigator
from services.nav.pose_tracker import PoseTracker

RES = 0.05


def odom(stamp: float, x: float, y: float = 0.0, theta: float = 0.0) -> m.Odometry:
    return m.Odometry(stamp=stamp, pose=m.Pose2D(x=x, y=y, theta=theta))


def pose_msg(stamp: float, x: float, y: float, theta: float, state: str = "tracking") -> m.PoseWithCovariance:
    return m.PoseWithCovariance(stamp=stamp, pose=m.Pose2D(x=x, y=y, theta=theta), state=state)  # type: ignore[arg-type]


# --------------------------------------------------------------------------- PoseTracker


def test_pose_is_map_odom_composed_with_odometry_or_the_last_pose_moved_on() -> None:
    t = PoseTracker()
    assert t.current() is None
    t.on_odom(odom(1.0, 1.0))
    t.on_pose(pose_msg(1.0, 5.0, 2.0, math.pi / 2))
    t.on_odom(odom(2.0, 2.0))  # 1 m forward in odom since the pose: +y in the map
    assert t.current() == pytest.approx((5.0, 3.0, math.pi / 2))
    jump = t.on_tf(m.Transform2D(stamp=2.0, x=10.0, y=0.0, theta=0.0))  # the pose goes (5, 3) -> (12, 0)
    assert jump == pytest.approx((math.hypot(7.0, 3.0), math.pi / 2))
    assert t.current() == pytest.approx((12.0, 0.0, 0.0))
    assert t.last_update() == 2.0
    t.on_odom(odom(1.5, 0.0))  # time went back (a restarted simulator): the history restarts
    assert list(t.odom_history) == [(1.5, (0.0, 0.0, 0.0))]


def test_odom_is_interpolated_along_the_shorter_arc_and_scans_are_placed_per_beam() -> None:
    t = PoseTracker()
    t.on_odom(odom(0.0, 0.0, 0.0, 3.0))
    t.on_odom(odom(1.0, 1.0, 0.0, -3.0))
    mid = t.odom_at(0.5)
    assert mid is not None and mid[0] == pytest.approx(0.5)
    assert abs(wrap_angle(mid[2] - math.pi)) < 1e-9  # through pi, not through 0
    assert t.odom_at(1.5) is None
    t.on_tf(m.Transform2D(stamp=1.0, x=0.0, y=0.0, theta=0.0))
    scan = m.LaserScan(stamp=0.0, angle_min=0.0, angle_increment=0.1, time_increment=0.5, range_min=0.1,
                       range_max=10.0, ranges=np.array([1.0, 1.0, 1.0], dtype="<f4").tobytes(),
                       mount=m.Pose2D(x=0.5))
    obs = t.scan_observation(scan)
    assert obs is not None
    x_first, x_last = 0.5 * math.cos(3.0), 1.0 + 0.5 * math.cos(-3.0)  # sensor at the first and the last beam
    np.testing.assert_allclose(obs.origin_x, [x_first, (x_first + x_last) / 2, x_last], atol=1e-9)
    assert t.scan_observation(m.LaserScan(stamp=0.0, angle_increment=0.0, ranges=b"")) is None


# --------------------------------------------------------------------------- NavCycle


def free_room() -> Navigator:
    nav = Navigator(NavConfig(), RobotSpec())
    nav.set_map(np.zeros((120, 200), np.int8), RES, 0.0, 0.0)
    return nav


def tracked(t: float, x: float = 2.0, state: str = "tracking") -> PoseTracker:
    tracker = PoseTracker()
    tracker.on_odom(odom(t, x, 3.0))
    tracker.on_tf(m.Transform2D(stamp=t, x=0.0, y=0.0, theta=0.0))
    tracker.on_pose(pose_msg(t, x, 3.0, 0.0, state))
    return tracker


def test_goal_drives_then_one_zero_twist_when_it_ends() -> None:
    nav, tracker = free_room(), tracked(0.0)
    cycle = NavCycle(NavConfig(), nav, tracker, 0.0)
    first = cycle.tick(0.0, planner_idle=True)
    assert first.publish_costmap and first.cmd is None and first.publish_status_now
    assert cycle.status_to_publish(0.0) is not None and cycle.status_to_publish(0.0) is None  # only on change
    ok, gid, _ = nav.start_goal(0.0, (6.0, 3.0, 0.0), "g1")
    assert ok
    out = cycle.tick(0.05, planner_idle=True)
    assert out.plan_request is not None and out.cmd is not None and out.local_plan is not None
    assert cycle.status_to_publish(0.05).goal_id == gid
    nav.cancel(gid)
    end = cycle.tick(0.1, planner_idle=True)
    assert end.cmd == (0.0, 0.0, 0.0) and end.local_plan is not None and len(end.local_plan) == 0
    assert any("canceled" in line for _, line in end.log)
    assert cycle.tick(0.15, planner_idle=True).cmd is None


def test_untrusted_localization_holds_the_goal_then_fails_it() -> None:
    cfg = NavConfig()
    nav, tracker = free_room(), tracked(0.0, state="lost")
    cycle = NavCycle(cfg, nav, tracker, 0.0)
    nav.start_goal(0.0, (6.0, 3.0, 0.0), "g1")
    held = cycle.tick(0.0, planner_idle=True)
    assert held.cmd == (0.0, 0.0, 0.0) and held.plan_request is None
    assert held.log[0][0] == logging.WARNING and "holding goal g1" in held.log[0][1]
    tracker.on_odom(odom(cfg.localization_lost_timeout_s + 1.0, 2.0, 3.0))
    failed = cycle.tick(cfg.localization_lost_timeout_s + 1.0, planner_idle=True)
    assert nav.state == "failed" and failed.cmd == (0.0, 0.0, 0.0)  # the one zero twist at the end


def test_stale_pose_stops_the_robot() -> None:
    cfg = NavConfig()
    nav, tracker = free_room(), tracked(0.0)
    cycle = NavCycle(cfg, nav, tracker, 0.0)
    nav.start_goal(0.0, (6.0, 3.0, 0.0), "g1")
    out = cycle.tick(cfg.pose_timeout_s + 0.5, planner_idle=False)
    assert out.cmd == (0.0, 0.0, 0.0) and out.plan_request is None


def test_a_pose_jump_clears_the_obstacle_layers_and_only_the_answer_reaches_the_navigator() -> None:
    cfg = NavConfig()
    nav, tracker = free_room(), tracked(0.0)
    cycle = NavCycle(cfg, nav, tracker, 0.0)
    assert cycle.on_tf(m.Transform2D(stamp=0.1, x=0.01)) is None
    line = cycle.on_tf(m.Transform2D(stamp=0.2, x=cfg.clear_on_pose_jump_m + 0.5))
    assert line is not None and "obstacle layers cleared" in line
    nav.start_goal(0.0, (6.0, 3.0, 0.0), "g1")
    assert nav.goal is not None
    nav.goal.loc_requested_at = 0.0
    cycle.on_pose(1.0, pose_msg(1.0, 2.0, 3.0, 0.0))
    assert not nav.goal.loc_answered  # a pose on the topic is not the answer: it may predate the update
    cycle.on_localization_answer(2.0, m.LocalizationUpdate(ok=False, message="no scan"))
    assert nav.goal.loc_answered and not nav.goal.loc_updated and nav.goal.loc_updated_at == 2.0


def update_answer(stamp: float, map_odom_y: float, pose_y: float) -> m.LocalizationUpdate:
    return m.LocalizationUpdate(ok=True, pose=pose_msg(stamp, 2.0, pose_y, 0.0),
                                map_odom=m.Transform2D(stamp=stamp, y=map_odom_y))


def test_the_answer_to_an_update_moves_the_pose_before_the_navigator_hears_of_it() -> None:
    """The refined map->odom travels in the answer: the pose nav judges includes it even when the tf/map_odom
    message comes later (or never), and an answer older than a tf already in hand does not undo that tf."""
    nav, tracker = free_room(), tracked(0.0)
    cycle = NavCycle(NavConfig(), nav, tracker, 0.0)
    nav.start_goal(0.0, (6.0, 3.0, 0.0), "g1")
    assert nav.goal is not None
    nav.goal.loc_requested_at = 0.0
    cycle.on_localization_answer(1.0, update_answer(0.9, 0.07, 3.07))
    assert nav.goal.loc_answered and nav.goal.loc_updated
    assert tracker.current() == pytest.approx((2.0, 3.07, 0.0))
    cycle.on_tf(m.Transform2D(stamp=1.5, y=0.08))  # a later update
    cycle.on_localization_answer(1.6, update_answer(0.9, 0.07, 3.07))  # a stale answer (a second request)
    assert tracker.current() == pytest.approx((2.0, 3.08, 0.0))


def test_periodic_status_and_costmaps_carry_on_after_the_clock_restarts() -> None:
    """A simulator restart sets sim time back to 0: the status, costmap and replan schedules re-anchor at once
    instead of waiting until the new run's clock catches up with the old one."""
    cfg = NavConfig()
    nav, tracker = free_room(), tracked(0.0)
    cycle = NavCycle(cfg, nav, tracker, 0.0)
    t = 0.0
    while t < 20.0:
        cycle.tick(t, planner_idle=True)
        t += 0.05
    for restarted_at in (0.01, 0.06):
        assert cycle.tick(restarted_at, planner_idle=True).publish_status_now or restarted_at > 0.01
    publishes = sum(cycle.tick(0.1 + 0.05 * k, planner_idle=True).publish_status_now for k in range(40))
    assert publishes >= 2 * cfg.status_frequency_hz - 1, f"{publishes} status messages in the 2 s after a restart"


def test_a_replan_is_due_again_after_the_clock_restarts() -> None:
    nav = free_room()
    ok, _, _ = nav.start_goal(30.0, (6.0, 3.0, 0.0), "g1")
    assert ok and nav.goal is not None
    nav.goal.plan_now = False
    nav.goal.last_plan_at = 30.0
    assert not nav.plan_due(30.1)
    assert nav.plan_due(0.2), "no replan until the new run's clock reaches the old run's 30 s"
