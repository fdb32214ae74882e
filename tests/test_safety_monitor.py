"""The collision monitor core: zones judged along the commanded direction, approach scaling, fail-safe on no scan."""

import math

import numpy as np
import pytest

from services.safety.monitor import CollisionMonitor, SafetyParams, scan_points

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
