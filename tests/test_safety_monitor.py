"""The collision monitor core: zones judged along the commanded direction, approach scaling, fail-safe on no scan."""

import math

import numpy as np
import pytest

from services.common.se2 import inverse, transform_points
from services.safety.monitor import CollisionMonitor, FieldOfView, SafetyParams, scan_points

R = 0.63


def wall_x(x_m: float, half_width_m: float = 3.0, step_m: float = 0.02) -> np.ndarray:
    """Points of a wall across the robot's way at x = x_m (base frame)."""
    y = np.arange(-half_width_m, half_width_m + 1e-9, step_m)
    return np.column_stack((np.full_like(y, x_m), y))


def monitor_with(points: np.ndarray, stamp: float = 0.0, **kw: float) -> CollisionMonitor:
    mon = CollisionMonitor(SafetyParams(**kw))
    mon.update_scan(points, stamp)
    return mon


def test_no_scan_and_stale_scan_stop_everything():
    mon = CollisionMonitor(SafetyParams())
    v = mon.filter(0.2, 0.0, 0.3, now=1.0)
    assert v.twist == (0.0, 0.0, 0.0) and v.action == "no_scan" and "no scan" in v.reason
    mon.update_scan(wall_x(10.0), 1.0)
    assert mon.filter(0.2, 0.0, 0.0, now=1.2).action == "clear"
    v = mon.filter(0.2, 0.0, 0.0, now=1.6)
    assert v.twist == (0.0, 0.0, 0.0) and v.action == "no_scan" and "0.60 s old" in v.reason


def test_a_scan_from_before_a_clock_restart_is_not_fresh():
    mon = monitor_with(wall_x(10.0), stamp=24.0)  # the last scan of a simulator run that then restarted at 0
    v = mon.filter(0.2, 0.0, 0.0, now=0.05)
    assert v.twist == (0.0, 0.0, 0.0) and v.action == "no_scan" and "clock restarted" in v.reason


def test_non_finite_command_is_zeroed():
    mon = monitor_with(wall_x(10.0))
    assert mon.filter(math.nan, 0.0, 0.0, now=0.0).twist == (0.0, 0.0, 0.0)


def test_wall_ahead_stops_translation_but_backing_away_and_turning_pass():
    mon = monitor_with(wall_x(R + 0.03))
    v = mon.filter(0.2, 0.0, 0.4, now=0.0)
    assert v.action == "stop" and v.twist == (0.0, 0.0, 0.4) and v.nearest_m == pytest.approx(0.03, abs=1e-6)
    assert mon.filter(-0.1, 0.0, 0.0, now=0.0).twist == (-0.1, 0.0, 0.0)  # away from it
    assert mon.filter(0.0, 0.0, 0.5, now=0.0).action == "clear"  # a circle turning in place sweeps nothing


def test_holonomic_direction_decides_which_points_matter():
    # a wall 0.03 m to the left of the footprint: driving along it is fine, strafing into it is not
    y = R + 0.03
    x = np.arange(-3.0, 3.0, 0.02)
    mon = monitor_with(np.column_stack((x, np.full_like(x, y))))
    assert mon.filter(0.2, 0.0, 0.0, now=0.0).action == "clear"
    v = mon.filter(0.0, 0.2, 0.0, now=0.0)
    assert v.action == "stop" and v.twist[:2] == (0.0, 0.0)
    assert mon.filter(0.0, -0.2, 0.0, now=0.0).action == "clear"
    # diagonally towards it: the band the footprint sweeps reaches the wall
    assert mon.filter(0.14, 0.14, 0.0, now=0.0).action == "stop"


def test_slowdown_zone_and_approach_scaling():
    mon = monitor_with(wall_x(R + 0.25), slowdown_margin_m=0.35, slowdown_ratio=0.4, time_before_collision_s=1.5)
    v = mon.filter(0.2, 0.0, 0.0, now=0.0)
    # contact after 0.25 m at 0.2 m/s = 1.25 s < 1.5 s: approach scale 0.833 is weaker than the slow-down 0.4
    assert v.action == "slowdown" and v.twist[0] == pytest.approx(0.08)
    mon = monitor_with(wall_x(R + 0.2), slowdown_margin_m=0.1, time_before_collision_s=1.5, simulation_step_s=0.01)
    v = mon.filter(0.2, 0.0, 0.0, now=0.0)
    assert v.action == "approach" and v.scale == pytest.approx(1.0 / 1.5, abs=0.02)
    assert v.twist[0] == pytest.approx(0.2 * v.scale)


def test_approach_follows_the_arc_of_a_turning_command():
    # an obstacle to the front-left is reached only if the robot curves left
    mon = monitor_with(np.array([[0.6, 1.1]]), stop_margin_m=0.0, slowdown_margin_m=0.0,
                       time_before_collision_s=6.0)
    assert mon.filter(0.2, 0.0, 0.0, now=0.0).action == "clear"
    assert mon.filter(0.2, 0.0, 0.5, now=0.0).action == "approach"


def test_scan_points_apply_the_mount_and_drop_invalid_returns():
    ranges = np.array([1.0, np.inf, 0.01, 2.0, np.nan], dtype=np.float32)
    pts = scan_points(ranges, -math.pi / 2, math.pi / 4, 0.05, 20.0, (0.45, 0.0, math.pi))
    # beam 0: bearing -pi/2 + pi = pi/2 -> (0.45, 1.0); beam 3: bearing pi/4 + pi -> 0.45 - 2 cos 45°
    assert pts.shape == (2, 2)
    assert pts[0] == pytest.approx([0.45, 1.0], abs=1e-6)
    assert pts[1] == pytest.approx([0.45 - math.sqrt(2.0), -math.sqrt(2.0)], abs=1e-6)


def test_bad_parameters_are_named():
    with pytest.raises(ValueError, match="slowdown_ratio"):
        CollisionMonitor(SafetyParams(slowdown_ratio=2.0))


def test_no_contact_when_commands_drive_into_a_wall_at_full_speed():
    """Closed loop: a point robot model driven at 0.2 m/s at a wall stops short of it and never touches it."""
    mon = CollisionMonitor(SafetyParams())
    x, dt = 0.0, 0.02
    wall = 3.0
    for k in range(2000):
        mon.update_scan(wall_x(wall - x), k * dt)
        vx = mon.filter(0.2, 0.0, 0.0, now=k * dt).twist[0]
        x += vx * dt
    assert wall - x - R > 0.0
    assert wall - x - R < 0.06  # it does get close: the zones do not keep it needlessly far


# --------------------------------------------------------------------------- the scanner's blind sector

LMS111 = FieldOfView(mount=(0.45, 0.0, 0.0), angle_min=-3 * math.pi / 4, angle_max=3 * math.pi / 4)


def seen_from(odom_pose: tuple[float, float, float], odom_points: np.ndarray) -> np.ndarray:
    """What the front 270° scanner sees of odom-frame points from a base pose (base frame; no occlusion)."""
    base = transform_points(inverse(odom_pose), odom_points)
    return base[LMS111.sees(base)]


def test_field_of_view_covers_270_degrees_in_front_of_the_scanner():
    pts = np.array([[2.0, 0.0], [0.45, 1.0], [0.45, -1.0], [-1.0, 0.0], [-1.0, 1.2], [-1.0, 1.6]])
    assert LMS111.sees(pts).tolist() == [True, True, True, False, False, True]


def test_a_wall_behind_the_robot_stops_a_back_up_it_saw_before_turning():
    """The scanner cannot see behind the base. A wall seen ahead is remembered (odometry) once the robot has turned
    its back to it, and backing into it stops; without the memory the back-up was judged on no points at all."""
    wall = np.column_stack((np.full(301, -(R + 0.03)), np.linspace(-3.0, 3.0, 301)))  # odom frame, x = -0.66
    mon = CollisionMonitor(SafetyParams())
    facing = (0.0, 0.0, math.pi)
    mon.update_scan(seen_from(facing, wall), 0.0, facing, LMS111)
    assert mon.filter(0.2, 0.0, 0.0, now=0.0).action == "stop"  # ahead: seen
    for k in range(1, 33):  # turn in place to face away from it, a scan every 0.1 rad
        pose = (0.0, 0.0, math.pi - 0.1 * k)
        mon.update_scan(seen_from(pose, wall), 0.04 * k, pose, LMS111)
    now = 0.04 * 32
    assert np.abs(seen_from(pose, wall)[:, 1]).min() > R  # the scan shows nothing of the wall the back-up meets
    v = mon.filter(-0.1, 0.0, 0.0, now=now)
    assert v.action == "stop" and v.twist[:2] == (0.0, 0.0), v
    assert mon.filter(0.2, 0.0, 0.0, now=now).action == "clear"  # driving away from it is fine
    forgetful = CollisionMonitor(SafetyParams())
    forgetful.update_scan(seen_from(pose, wall), now)  # no odometry: the scan alone, as before
    assert forgetful.filter(-0.1, 0.0, 0.0, now=now).action == "clear"


def test_a_remembered_point_is_forgotten_once_the_scanner_sees_the_place_again():
    person = np.array([[-0.9, 0.0]])  # behind the robot, seen earlier, then walked away
    mon = CollisionMonitor(SafetyParams())
    mon.update_scan(seen_from((0.0, 0.0, math.pi), person), 0.0, (0.0, 0.0, math.pi), LMS111)
    mon.update_scan(np.zeros((0, 2)), 0.1, (0.0, 0.0, 0.0), LMS111)  # turned back: it is behind, remembered
    assert mon.filter(-0.1, 0.0, 0.0, now=0.1).action != "clear"
    mon.update_scan(np.zeros((0, 2)), 0.2, (0.0, 0.0, math.pi), LMS111)  # looked again: nobody there
    mon.update_scan(np.zeros((0, 2)), 0.3, (0.0, 0.0, 0.0), LMS111)
    assert mon.filter(-0.1, 0.0, 0.0, now=0.3).action == "clear"
    # seen, then 1.2 m of driving away from it: beyond memory_travel_m (odometry drift), dropped
    mon = CollisionMonitor(SafetyParams(memory_travel_m=1.0))
    mon.update_scan(seen_from((0.0, 0.0, math.pi), person), 0.0, (0.0, 0.0, math.pi), LMS111)
    for k in range(7):
        mon.update_scan(np.zeros((0, 2)), 0.1 * (k + 1), (0.2 * k, 0.0, 0.0), LMS111)
        assert len(mon.points) == (1 if 0.2 * k <= 1.0 + 1e-9 else 0), k  # judged while remembered


def test_no_contact_backing_into_a_wall_the_scanner_cannot_see_any_more():
    """Closed loop: the robot sees a wall, turns its back to it and is told to back up at full speed; the
    remembered points stop it short of the wall."""
    wall = np.column_stack((np.full(301, -1.5), np.linspace(-3.0, 3.0, 301)))
    mon = CollisionMonitor(SafetyParams())
    t, dt = 0.0, 0.02
    for k in range(80):  # turn from facing the wall to facing away at 0.5 rad/s
        pose = (0.0, 0.0, math.pi - min(0.01 * k * 4, math.pi))
        mon.update_scan(seen_from(pose, wall), t, pose, LMS111)
        t += dt
    x = 0.0
    for _ in range(1200):
        pose = (x, 0.0, 0.0)
        mon.update_scan(seen_from(pose, wall), t, pose, LMS111)
        x += mon.filter(-0.1, 0.0, 0.0, now=t).twist[0] * dt
        t += dt
    assert x - R - (-1.5) > 0.0  # never touched
    assert x - R - (-1.5) < 0.06  # and it did back up to it


# --------------------------------------------------------------------------- late scans carried by odometry


def odom_trace(mon: CollisionMonitor, poses: list[tuple[float, tuple[float, float, float]]]) -> None:
    for stamp, pose in poses:
        mon.note_odom(stamp, pose)


def test_a_late_scan_is_judged_where_odometry_says_the_base_is_now():
    """Wall 2.0 m ahead when scanned at t = 0; by t = 1.0 odometry has the base 1.30 m further on: 0.07 m from the
    footprint, inside the slow-down zone, and 1.34 m on it is inside the stop zone. Unshifted it would be clear."""
    for moved_m, action in ((1.30, "slowdown"), (1.34, "stop"), (0.5, "clear")):
        mon = monitor_with(wall_x(2.0), stamp=0.0, time_before_collision_s=0.05, simulation_step_s=0.05)
        odom_trace(mon, [(0.02 * k, (moved_m * k / 50, 0.0, 0.0)) for k in range(51)])
        v = mon.filter(0.2, 0.0, 0.0, now=1.0)
        assert v.action == action, (moved_m, v)
        if action != "clear":
            assert v.nearest_m == pytest.approx(2.0 - moved_m - R, abs=1e-6)


def test_a_turn_since_the_scan_moves_the_wall_beside_the_robot():
    mon = monitor_with(wall_x(R + 0.2), stamp=0.0)
    odom_trace(mon, [(0.1 * k, (0.0, 0.0, math.pi / 2 * k / 10)) for k in range(11)])  # quarter turn left by t = 1
    assert mon.filter(0.2, 0.0, 0.0, now=1.0).action == "clear"  # the wall is now on the right
    assert mon.filter(0.0, -0.2, 0.0, now=1.0).action in ("slowdown", "approach")  # strafing right meets it


def test_late_scan_limits_odometry_cannot_lift():
    # older than scan_timeout_s: stop, even with odometry
    mon = monitor_with(wall_x(10.0), stamp=0.0)
    odom_trace(mon, [(0.1 * k, (0.0, 0.0, 0.0)) for k in range(22)])
    assert mon.filter(0.2, 0.0, 0.0, now=1.9).action == "clear"
    v = mon.filter(0.2, 0.0, 0.0, now=2.1)
    assert v.action == "no_scan" and "2.10 s old" in v.reason
    # odometry that stopped (a CAN link loss) cannot carry a scan past the uncorrected limit
    mon = monitor_with(wall_x(10.0), stamp=0.0)
    odom_trace(mon, [(0.1 * k, (0.0, 0.0, 0.0)) for k in range(4)])  # last pose at 0.3 s
    assert mon.filter(0.2, 0.0, 0.0, now=0.75).action == "clear"
    v = mon.filter(0.2, 0.0, 0.0, now=0.9)
    assert v.action == "no_scan" and "no odometry to carry it" in v.reason
    # odometry that does not reach back to the scan's stamp cannot place it either
    mon = monitor_with(wall_x(10.0), stamp=0.0)
    odom_trace(mon, [(0.5 + 0.1 * k, (0.0, 0.0, 0.0)) for k in range(5)])
    assert mon.filter(0.2, 0.0, 0.0, now=0.9).action == "no_scan"
    # correction switched off: the uncorrected limit holds
    mon = monitor_with(wall_x(10.0), stamp=0.0, base_shift_correction=False)
    odom_trace(mon, [(0.1 * k, (0.0, 0.0, 0.0)) for k in range(10)])
    assert mon.filter(0.2, 0.0, 0.0, now=0.9).action == "no_scan"


def test_odometry_history_interpolates_and_restarts_with_the_clock():
    mon = CollisionMonitor(SafetyParams())
    odom_trace(mon, [(1.0, (0.0, 0.0, 3.0)), (2.0, (1.0, 0.0, -3.0))])
    x, y, theta = mon.odom_at(1.5) or (math.nan,) * 3
    assert (x, y) == pytest.approx((0.5, 0.0)) and abs(abs(theta) - math.pi) < 1e-9  # the short way round ±pi
    assert mon.odom_at(0.9) is None and mon.odom_at(2.4) == (1.0, 0.0, -3.0) and mon.odom_at(2.6) is None
    mon.note_odom(0.05, (5.0, 5.0, 0.0))  # the simulator restarted at 0: the old history is gone
    assert mon.odom_at(1.5) is None and mon.odom_at(0.05) == (5.0, 5.0, 0.0)
    mon.note_odom(0.1, (math.nan, 0.0, 0.0))  # non-finite poses are not noted
    assert mon.odom_at(0.1) == (5.0, 5.0, 0.0)


def test_closed_loop_with_scans_a_second_late_still_never_touches():
    """The scan arrives 1.0 s after it was taken (load); odometry carries it. Driving at a wall at 0.2 m/s, the
    robot stops short of it and does not touch it."""
    mon = CollisionMonitor(SafetyParams())
    x, dt, wall, lag_steps = 0.0, 0.02, 3.0, 50
    xs = [0.0]
    for k in range(1, 2000):
        mon.note_odom(k * dt, (x, 0.0, 0.0))
        if k >= lag_steps:
            seen_at = k - lag_steps
            mon.update_scan(wall_x(wall - xs[seen_at]), seen_at * dt)
        vx = mon.filter(0.2, 0.0, 0.0, now=k * dt).twist[0] if k >= lag_steps else 0.0
        x += vx * dt
        xs.append(x)
    assert 0.0 < wall - x - R < 0.08
