"""Several robots in one simulated world: placement, lidars that see other chassis, robot-robot contact."""

from __future__ import annotations

import math
import os

import msgspec
import numpy as np
import pytest

from services.common.robot import RobotSpec
from services.common.world import World, WorldError
from services.sim.config import SimConfig, SimRobot
from services.sim.fleet import Fleet, start_poses
from services.sim.scan_source import Body, ray_discs

RADIUS_M = 0.63


@pytest.fixture(scope="module")
def room() -> World:
    return World.load_builtin("empty_room")


def drive_forward(fleet: Fleet, rid: str, rpm: float) -> None:
    """Both wheels straight ahead (steer at zero counts) at ``rpm``: the robot moves along its heading."""
    for module in fleet.sims[rid].robot.modules:
        module.traction.target_rpm = rpm


def test_ray_discs_hits_the_near_face_and_misses_beside_it() -> None:
    angles = np.array([0.0, math.pi / 2, math.atan2(0.5, 3.0), math.atan2(0.7, 3.0)])
    r = ray_discs(0.0, 0.0, angles, [Body(3.0, 0.0, 0.5)], 20.0)
    assert r[0] == pytest.approx(2.5)
    assert r[1] == 20.0  # beside it
    assert 2.5 < r[2] < 3.1  # grazing the disc
    assert r[3] == 20.0  # just past its edge (0.7 / 3.04 > 0.5 / 3)
    # behind the laser or beyond the range: no hit; inside a disc: not blocked by it
    assert ray_discs(0.0, 0.0, np.array([math.pi]), [Body(3.0, 0.0, 0.5)], 20.0)[0] == 20.0
    assert ray_discs(0.0, 0.0, np.array([0.0]), [Body(30.0, 0.0, 0.5)], 20.0)[0] == 20.0
    assert ray_discs(0.0, 0.0, np.array([0.0]), [Body(0.1, 0.0, 0.5)], 20.0)[0] == 20.0


def test_each_lidar_sees_the_other_robots_chassis(room: World) -> None:
    cfg = SimConfig(laser_noise_m=0.0)
    fleet = Fleet(cfg, RobotSpec(), room, ["a", "b"], [(-3.0, 0.0, 0.0), (0.0, 0.0, math.pi)])
    # a's laser sits 0.45 m ahead of its centre: b's chassis face is 3.0 - 0.63 - 0.45 = 1.92 m straight ahead
    _, ranges = fleet.sims["a"].scan_source.laser_ranges(np.array([0.0, 0.3]))
    assert ranges[0] == pytest.approx(3.0 - RADIUS_M - 0.45, abs=1e-6)
    # the same beam in a lone robot's world reaches the crate or the wall, much further away
    alone = Fleet(cfg, RobotSpec(), room, ["a"], [(-3.0, 0.0, 0.0)])
    assert alone.sims["a"].scan_source.laser_ranges(np.array([0.0]))[1][0] > 4.0
    # b sees a the same way, and after a moves away it no longer does
    assert fleet.sims["b"].scan_source.laser_ranges(np.array([0.0]))[1][0] == pytest.approx(1.92, abs=1e-6)
    fleet.teleport("a", -3.0, 3.0, 0.0)
    assert fleet.sims["b"].scan_source.laser_ranges(np.array([0.0]))[1][0] > 2.5


def test_robots_stop_at_contact_and_both_report_it(room: World) -> None:
    fleet = Fleet(SimConfig(), RobotSpec(), room, ["a", "b"], [(-3.0, -2.0, 0.0), (0.0, -2.0, 0.0)])
    drive_forward(fleet, "a", 1500.0)  # ~0.52 m/s towards b, which stands still
    for _ in range(2000):  # 10 s: a would travel 5 m
        fleet.step()
        if fleet.sims["a"].robot.collided:
            break
    a, b = fleet.sims["a"].robot, fleet.sims["b"].robot
    assert a.collided and b.collided
    assert fleet.contact_with == {"a": "b", "b": "a"}
    gap = math.hypot(a.x - b.x, a.y - b.y) - 2 * RADIUS_M
    assert 0.0 <= gap < 0.01  # stopped at the touching distance, not inside
    for _ in range(200):  # pushing on does not move it deeper
        fleet.step()
    assert math.hypot(a.x - b.x, a.y - b.y) - 2 * RADIUS_M >= 0.0
    # a wall contact names the wall; a teleport clears the latch
    fleet.teleport("a", -3.0, 2.0, math.pi)
    assert not a.collided and fleet.contact_with["a"] == ""
    drive_forward(fleet, "a", 1500.0)
    for _ in range(2000):
        fleet.step()
        if a.collided:
            break
    assert fleet.contact_with["a"] == "wall"


def test_start_overlapping_another_robot_is_a_contact(room: World) -> None:
    fleet = Fleet(SimConfig(), RobotSpec(), room, ["a", "b"], [(0.0, -2.0, 0.0), (1.0, -2.0, 0.0)])
    assert fleet.contact_with == {"a": "b", "b": "a"}


def test_start_poses_are_spaced_free_and_keep_given_ones(room: World) -> None:
    poses = start_poses(room, 4, RADIUS_M)
    assert poses[0] == room.start_pose  # the first at the world's start
    for i, p in enumerate(poses):
        assert room.clearance_m(p[0], p[1]) >= RADIUS_M + 0.3 - 0.05
        for q in poses[:i]:
            assert math.hypot(p[0] - q[0], p[1] - q[1]) >= 2 * RADIUS_M + 0.6
    assert start_poses(room, 4, RADIUS_M) == poses  # deterministic
    given = [(-3.0, 2.0, 1.0)]
    assert start_poses(room, 2, RADIUS_M, given)[0] == given[0]
    with pytest.raises(ValueError, match="room for"):
        start_poses(room, 40, RADIUS_M)


def test_world_robots_table_is_read_and_checked() -> None:
    base = {"name": "w", "resolution_m": 0.1, "extent_m": [0, 0, 10, 10], "free": [[1, 1, 9, 9]]}
    w = World.from_dict({**base, "robots": [{"id": "a", "start": [2, 2, 0]}, {"id": "b", "start": [7, 7, 3.0]}]})
    assert w.robots == [("a", (2.0, 2.0, 0.0)), ("b", (7.0, 7.0, 3.0))]
    with pytest.raises(WorldError, match=r"robots\[1\].id"):
        World.from_dict({**base, "robots": [{"id": "a/b", "start": [2, 2, 0]}]})
    with pytest.raises(WorldError, match=r"robots\[2\].start"):
        World.from_dict({**base, "robots": [{"id": "a", "start": [2, 2, 0]}, {"id": "b", "start": [2, 2]}]})


def test_launcher_plans_one_simulator_and_a_stack_per_robot(tmp_path) -> None:
    import tomllib

    from services.launch.fleet import RobotSlot, fleet_slots, parse_robot_arg
    from services.launch.up import StackPlan, resolve_fleet

    assert parse_robot_arg("r7:1,2.5,-3") == RobotSlot("r7", (1.0, 2.5, -3.0))
    assert parse_robot_arg("left") == RobotSlot("left")
    for bad in ("a/b", "a:1,2", "a:1,2,x", "a:1,2,nan"):
        with pytest.raises(ValueError, match="--robot"):
            parse_robot_arg(bad)
    assert [s.id for s in fleet_slots(3, [RobotSlot("r2")], [])] == ["r2", "r1", "r3"]
    with pytest.raises(ValueError, match="distinct"):
        fleet_slots(2, [RobotSlot("a"), RobotSlot("a")], [])

    single = StackPlan(run_dir=str(tmp_path), headless=True)
    resolve_fleet(single)
    assert single.fleet == [] and single.robot_ids == ["r1"]
    assert [c.name for c in single.children()][:3] == ["canbus", "sim", "drive"]
    # hmi_api alone runs with 2 malloc arenas (docs/performance.md)
    envs = {c.name: c.env for c in StackPlan(run_dir=str(tmp_path)).children()}
    if "MALLOC_ARENA_MAX" not in os.environ:
        assert envs["hmi_api"].get("MALLOC_ARENA_MAX") == "2" and "MALLOC_ARENA_MAX" not in envs["nav"]

    plan = StackPlan(run_dir=str(tmp_path), headless=True, robot_count=3, can_port=5000, lidar_port=6000)
    resolve_fleet(plan)
    assert plan.robot_ids == ["r1", "r2", "r3"]
    assert plan.fleet[0].start == World.load_builtin("corridor").start_pose
    names = [c.name for c in plan.children()]
    assert names.count("sim") == 1 and {"r1.canbus", "r3.canbus", "r2.drive", "r3.nav"} <= set(names)
    assert plan.expected_tokens() >= {"r1.sim", "r2.sim", "r3.sim", "r3.localization"}
    specs = {c.name: c.argv for c in plan.children()}
    assert "--port" in specs["r3.canbus"] and "5002" in specs["r3.canbus"]
    assert "lidar.port=6002" in specs["r3.lidar"] and "r3" in specs["r3.lidar"]
    assert 'drive.can_channel="ws://127.0.0.1:5001/"' in specs["r2.drive"]
    loc = " ".join(specs["r2.localization"])
    assert f"localization.initial_pose_x={plan.fleet[1].start[0]!r}" in loc and str(tmp_path / "r2") in loc
    # the simulator's robots table parses into its config, each robot on its own bus and port
    robots_set = next(a for a in specs["sim"] if a.startswith("sim.robots="))
    table = tomllib.loads("v = " + robots_set.split("=", 1)[1])["v"]
    cfg = SimConfig(robots=[msgspec.convert(t, SimRobot) for t in table])
    cfg.check()
    assert [(r.id, r.lidar_port, r.can_channel) for r in cfg.robots] == [
        ("r1", 6000, "ws://127.0.0.1:5000/"), ("r2", 6001, "ws://127.0.0.1:5001/"), ("r3", 6002, "ws://127.0.0.1:5002/")]
    assert [tuple(r.start_pose) for r in cfg.robots] == [s.start for s in plan.fleet]
