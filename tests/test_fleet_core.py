"""The fleet view's core (services/fleet/core.py): presence, poses, paths, battery, faults, the site map."""

from __future__ import annotations

import math

import numpy as np
import pytest

from proto.messages import (
    ModuleState,
    NavStatus,
    OccupancyGrid,
    Odometry,
    Path,
    Pose2D,
    PoseWithCovariance,
    SafetyState,
    Transform2D,
    WheelStates,
)
from services.fleet.core import FleetView, battery_percent, decimated_path

BATTERY = (44.0, 52.0)


def snapshot(view: FleetView) -> dict[str, dict]:
    return {r["id"]: r for r in view.snapshot(0.63, BATTERY, 400)["robots"]}


def test_presence_follows_the_health_tokens_and_events_say_who_left_and_came_back() -> None:
    view = FleetView(own_id="site")
    assert view.on_health("r1", "nav", True, 10.0) == "joined"
    assert view.on_health("r1", "drive", True, 10.1) is None
    assert view.on_health("r1", "nav", False, 11.0) is None, "one service gone: the robot is still there"
    assert view.on_health("r1", "drive", False, 12.0) == "left"
    assert view.on_health("r1", "drive", True, 15.0) == "joined"
    assert [e["event"] for e in view.events] == ["joined", "left", "joined"]
    assert view.robots["r1"].leaves == 1 and view.robots["r1"].left_at_s == 12.0
    assert view.on_health("site", "fleet", True, 1.0) is None and "site" not in view.robots


def test_only_the_robots_listed_are_shown() -> None:
    view = FleetView(own_id="site", robots_shown=["r2"])
    view.on_health("r1", "nav", True, 0.0)
    view.on_message("r1", "odom", Odometry())
    view.on_health("r2", "nav", True, 0.0)
    assert list(view.robots) == ["r2"]


def test_the_map_pose_composes_map_odom_with_odometry_as_the_robot_hmi_does() -> None:
    view = FleetView()
    view.on_message("r1", "odom", Odometry(pose=Pose2D(x=1.0, y=0.0, theta=0.5)))
    assert snapshot(view)["r1"]["pose"]["frame"] == "odom"
    view.on_message("r1", "tf/map_odom", Transform2D(x=2.0, y=1.0, theta=math.pi / 2))
    pose = snapshot(view)["r1"]["pose"]
    assert (pose["x"], pose["y"], pose["theta"]) == pytest.approx((2.0, 2.0, math.pi / 2 + 0.5), abs=1e-4)
    assert pose["frame"] == "map"


def test_battery_faults_state_and_path() -> None:
    view = FleetView()
    view.on_health("r1", "drive", True, 0.0)
    view.on_message("r1", "wheels", WheelStates(enabled=True, link_ok=False, estopped=True, fault="overcurrent",
                                                modules=[ModuleState(battery_v=48.0, fault_flags=0x4),
                                                         ModuleState(battery_v=math.nan)]))
    view.on_message("r1", "nav/status", NavStatus(state="failed", error="no path"))
    view.on_message("r1", "pose", PoseWithCovariance(state="lost"))
    view.on_message("r1", "safety/state", SafetyState(action="stop", reason="obstacle ahead"))
    r = snapshot(view)["r1"]
    assert r["battery"] == {"voltage_v": 48.0, "percent": 50.0}
    assert r["faults"] == ["e-stop", "drive: overcurrent", "drive: CAN link down", "module 0: fault flags 0x04",
                           "nav: no path", "localization lost", "safety: stop (obstacle ahead)"]
    assert r["drive"] == {"enabled": True, "estopped": True, "link_ok": False}
    assert r["nav"]["state"] == "failed" and r["localization"] == "lost"
    assert battery_percent(40.0, *BATTERY) == 0.0 and battery_percent(60.0, *BATTERY) == 100.0
    view.on_message("r1", "wheels", WheelStates(link_ok=True))
    assert snapshot(view)["r1"]["battery"] is None, "no voltage reported yet: no battery figure"


def test_a_long_path_is_decimated_keeping_its_ends() -> None:
    rows = np.stack([np.arange(1000, dtype=np.float32), np.zeros(1000, np.float32), np.zeros(1000, np.float32)], 1)
    flat = decimated_path(Path(poses=rows.astype("<f4").tobytes()), 50)
    assert len(flat) == 100 and flat[:2] == [0.0, 0.0] and flat[-2:] == [999.0, 0.0]
    assert decimated_path(None, 50) == [] and decimated_path(Path(), 50) == []
    nan_row = np.array([[math.nan, 1.0, 0.0]], dtype="<f4").tobytes()
    assert decimated_path(Path(poses=nan_row), 50) == [None, 1.0], "JSON has no NaN"


def test_the_site_map_comes_from_map_from_else_the_first_robot_by_id() -> None:
    grid = OccupancyGrid(width=2, height=1, data=np.zeros(2, np.int8).tobytes())
    other = OccupancyGrid(width=3, height=1, data=np.zeros(3, np.int8).tobytes())
    view = FleetView()
    assert view.site_map() is None
    view.on_message("r2", "map", other)
    assert view.site_map() == ("r2", other) and view.map_version == 1
    view.on_message("r1", "map", grid)
    assert view.site_map() == ("r1", grid) and view.map_version == 2
    chosen = FleetView(map_from="r2")
    chosen.on_message("r1", "map", grid)
    assert chosen.site_map() is None, "only r2's map is the site map"
    chosen.on_message("r2", "map", other)
    assert chosen.site_map() == ("r2", other)
