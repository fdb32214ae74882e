"""Mapping mode: the occupied-cell F1 used to score maps, and live SLAM in the simulator (sim + lidar +
localization + hmi_api via ``zagv up --mapping``): build the corridor map, save it, switch to AMCL on it, and the
same from the HMI's mapping endpoints.

Workflow test: the robot is moved by ``sim/teleport`` in small steps (4 cm / 0.04 rad every 40 ms, about 1 m/s)
through the lobby and along the main corridor to x = 6 m; the test publishes ``odom`` from ``sim/ground_truth`` with
a 1 % scale error. Acceptance test: the robot is driven by ``cmd_vel`` through the drive service through the lobby and
along the main corridor to x = 15 m. Saved maps are compared with the ground truth rendered by
``services.sim.render_map`` in the explored part, aligned by the shared start pose and refined by a ±2 cell search;
ground-truth walls count where the built map saw free space next to them.
"""

from __future__ import annotations

import asyncio
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from proto.messages import (
    InitialPoseRequest,
    ModeRequest,
    Pose2D,
    SaveMapRequest,
    Twist2D,
)
from services.common.map_io import FREE, OCCUPIED, load_map
from services.common.node import Node
from services.common.se2 import wrap_angle
from services.localization.slam.map_compare import best_aligned_f1, occupied_f1, surface
from services.localization.slam.map_files import read_trajectory
from tests.support.hmi import HmiClient, base_url, password_of
from tests.support.stats import service_stats
from tests.support.truth_odometry import TruthOdometryHarness
from tests.support.waiting import wait_for

EXPLORED = (-2.5, -2.0, 15.5, 5.5)  # x_min, y_min, x_max, y_max (m): the lobby and the main corridor to x = 15 m
LOBBY = (-2.5, -2.0, 6.5, 5.5)  # the lobby and the corridor to x = 6 m
MAPPING_ROUTE = [(0.0, 0.0, 0.0), (4.0, 0.1, 0.0), (4.0, 0.1, math.pi), (-1.0, 0.1, math.pi),
                 (-1.0, 0.3, math.pi / 2), (0.0, 3.2, 0.0), (15.0, 3.2, 0.0), (15.0, 3.2, math.pi), (6.0, 3.2, math.pi)]


# ------------------------------------------------------------------------------------------------ F1 (unit)

def _box(shape: tuple[int, int], lo: tuple[int, int], hi: tuple[int, int]) -> np.ndarray:
    """Boolean grid with the outline of the rectangle of cells lo..hi (row, col) set."""
    g = np.zeros(shape, bool)
    g[lo[0]:hi[0] + 1, [lo[1], hi[1]]] = True
    g[[lo[0], hi[0]], lo[1]:hi[1] + 1] = True
    return g


def test_f1_is_one_for_identical_maps_and_tolerates_one_cell():
    truth = _box((40, 60), (5, 5), (30, 50))
    same = occupied_f1(truth, 0.05, (0.0, 0.0), truth, 0.05, (0.0, 0.0))
    assert same.precision == same.recall == same.f1 == 1.0
    one_off = occupied_f1(np.roll(truth, 1, axis=1), 0.05, (0.0, 0.0), truth, 0.05, (0.0, 0.0))
    assert one_off.f1 == 1.0
    three_off = occupied_f1(np.roll(truth, 3, axis=1), 0.05, (0.0, 0.0), truth, 0.05, (0.0, 0.0))
    assert three_off.f1 < 0.7  # the two long walls still match, the two short ones do not
    strict = occupied_f1(np.roll(truth, 1, axis=1), 0.05, (0.0, 0.0), truth, 0.05, (0.0, 0.0), tolerance_cells=0)
    assert strict.f1 < 0.7


def test_f1_counts_missing_and_spurious_cells():
    truth = _box((40, 60), (5, 5), (30, 50))
    half = truth.copy()
    half[:, 28:] = False  # the built map saw only the west half
    r = occupied_f1(half, 0.05, (0.0, 0.0), truth, 0.05, (0.0, 0.0))
    assert r.precision == 1.0 and 0.4 < r.recall < 0.6
    noisy = truth.copy()
    noisy[15:20, 20:30] = True  # 50 spurious cells in free space
    r = occupied_f1(noisy, 0.05, (0.0, 0.0), truth, 0.05, (0.0, 0.0))
    assert r.recall == 1.0 and r.precision == pytest.approx(truth.sum() / noisy.sum())


def test_alignment_search_recovers_a_small_shift_and_grids_may_differ():
    truth = _box((40, 60), (5, 5), (30, 50))
    shifted = np.roll(truth, 2, axis=0)  # built map 2 cells (0.1 m) north of the truth
    assert occupied_f1(shifted, 0.05, (0.0, 0.0), truth, 0.05, (0.0, 0.0)).f1 < 0.8
    best = best_aligned_f1(shifted, 0.05, (0.0, 0.0), truth, 0.05, (0.0, 0.0), search_cells=3)
    # within the 1-cell tolerance, the smallest shift that matches everything: 1 cell south
    assert best.f1 == 1.0 and best.offset_xy_m == pytest.approx((0.0, -0.05))
    # the same outline in a bigger grid with another origin
    big = np.zeros((60, 80), bool)
    big[10:50, 10:70] = truth
    r = occupied_f1(big, 0.05, (-0.5, -0.5), truth, 0.05, (0.0, 0.0))
    assert r.f1 == 1.0


def test_surface_keeps_the_visible_boundary_and_region_limits_recall():
    solid = np.ones((20, 20), bool)
    solid[5:15, 5:15] = False
    boundary = surface(solid, ~solid)
    assert boundary.sum() == 4 * 12 - 4  # the ring around the 10 x 10 room, corners included
    built = boundary.copy()
    built[:, 10:] = False
    r = occupied_f1(built, 1.0, (0.0, 0.0), boundary, 1.0, (0.0, 0.0), region=(0.0, 0.0, 9.9, 20.0))
    assert r.f1 == 1.0
    built_free = np.zeros_like(solid)
    built_free[5:15, 5:8] = True  # only the west strip was seen free: the east walls were not observed
    r = occupied_f1(built, 1.0, (0.0, 0.0), boundary, 1.0, (0.0, 0.0), built_free=built_free, observed_cells=1)
    assert r.recall == 1.0


# ------------------------------------------------------------------------------------------------ simulator

def ground_truth(tmp_path: Path):
    out = tmp_path / "truth" / "corridor"
    subprocess.run([sys.executable, "-m", "services.sim.render_map", "--world", "corridor", "--out", str(out)],
                   check=True, capture_output=True)
    return load_map(out.with_suffix(".yaml"))


def map_f1(built_yaml: Path, truth, region: tuple[float, float, float, float] = EXPLORED) -> object:
    built = load_map(built_yaml)
    truth_occ = surface(truth.data == OCCUPIED, truth.data == FREE)
    return best_aligned_f1(built.data >= 65, built.resolution, built.origin[:2], truth_occ, truth.resolution,
                           truth.origin[:2], search_cells=2, region=region, built_free=built.data == FREE)


@pytest.mark.integration
@pytest.mark.slow
async def test_map_the_corridor_save_it_and_navigate_on_it(stack_factory, tmp_path):
    stack = stack_factory(services=["sim", "lidar", "localization", "hmi_api"], world="corridor",
                          extra_args=["--mapping"]).start()
    node = Node("mapping-test", stack.session(), stack.keys)
    h = TruthOdometryHarness(node)
    h.recording = True
    try:
        await wait_for(lambda: h.map_odom is not None, timeout_s=30, message="no tf/map_odom from mapping")
        refused = await node.query("localization/initial_pose", InitialPoseRequest(pose=Pose2D(x=1.0, y=0.0)))
        assert not refused.ok and "mapping" in refused.message
        started = asyncio.get_running_loop().time()
        await h.drive(MAPPING_ROUTE[:6] + [(6.0, 3.2, 0.0)])  # the lobby and the corridor to x = 6 m
        drive_s = asyncio.get_running_loop().time() - started
        errors = h.take_errors()[:, 1]
        stats = service_stats(stack, "localization")["mapping"]
        assert stats["processed"] > 50 and stats["skipped"] > stats["processed"]  # the motion gates let few through

        bad = await node.query("localization/save_map", SaveMapRequest(name="../escape"))
        assert not bad.ok and "name" in bad.message
        saved = await node.query("localization/save_map", SaveMapRequest(name="corridor_built"))
        assert saved.ok, saved.message
        yaml_path = Path(saved.message)
        assert yaml_path.name == "corridor_built.yaml" and yaml_path.with_suffix(".pgm").is_file()
        stamps, _ = read_trajectory(yaml_path.with_name("corridor_built.trajectory.txt"))
        assert len(stamps) >= stats["processed"] + stats["skipped"]  # every scan the mapper was given has a pose
        assert yaml_path.parent == stack.run_dir / "maps"

        agreement = map_f1(yaml_path, ground_truth(tmp_path), region=LOBBY)
        print(f"\nmapped {drive_s:.0f} s of teleport driving; SLAM pose error RMS "
              f"{float(np.sqrt(np.mean(errors ** 2))):.3f} m, max {errors.max():.3f} m; map vs ground truth "
              f"(x <= 6.5 m): precision {agreement.precision:.3f}, recall {agreement.recall:.3f}, "
              f"F1 {agreement.f1:.3f} at offset {agreement.offset_xy_m}; stats {stats}")
        assert agreement.f1 >= 0.9
        assert float(np.sqrt(np.mean(errors ** 2))) < 0.15  # teleport steps and scan latency add a few cm

        missing = await node.query("localization/mode", ModeRequest(mode="navigation", map_yaml="no_such_map"))
        assert not missing.ok
        switched = await node.query("localization/mode", ModeRequest(mode="navigation", map_yaml="corridor_built"))
        assert switched.ok, switched.message
        h.take_errors()
        h.map_odom = None
        await h.drive([(6.0, 3.2, 0.0), (6.0, 3.2, math.pi), (2.0, 3.2, math.pi)])
        assert h.map_odom is not None, "AMCL on the saved map published no tf/map_odom"
        nav_errors = h.take_errors()[:, 1]
        print(f"AMCL on the built map: RMS {float(np.sqrt(np.mean(nav_errors ** 2))):.3f} m over 4 m")
        assert float(np.sqrt(np.mean(nav_errors ** 2))) < 0.1
        ok = await node.query("localization/initial_pose", InitialPoseRequest(pose=Pose2D(x=2.0, y=3.2,
                                                                                          theta=math.pi)))
        assert ok.ok, ok.message
        not_mapping = await node.query("localization/save_map", SaveMapRequest(name="again"))
        assert not not_mapping.ok

        # the same workflow from the HMI: start mapping, save under a name, navigate on it
        with HmiClient(base_url(stack)) as client:
            assert client.post("/api/mapping/start").status_code == 401
            client.login(password_of(stack))
            r = client.post("/api/mapping/start")
            assert r.status_code == 200 and "mapping" in r.json()["message"], r.text
            await h.drive([(2.0, 3.2, math.pi), (2.0, 3.2, 0.0), (3.0, 3.2, 0.0)])
            assert client.post("/api/mapping/save", json={"name": "a/b"}).status_code == 422
            r = client.post("/api/mapping/save", json={"name": "from_hmi"})
            assert r.status_code == 200 and r.json()["message"].endswith("from_hmi.yaml"), r.text
            r = client.post("/api/mapping/stop", json={"map": "no_such_map"})
            assert r.status_code == 409, r.text
            r = client.post("/api/mapping/stop", json={"map": "from_hmi"})
            assert r.status_code == 200 and "navigation" in r.json()["message"], r.text
            assert client.post("/api/mapping/save", json={"name": "x"}).status_code == 409  # not mapping
    finally:
        node.close()


@pytest.mark.integration
@pytest.mark.slow
async def test_map_the_corridor_driving_through_the_drive_service(stack_factory, tmp_path):
    """sim + drive + lidar + localization (``--mapping``, sim at 3x): the robot is driven by cmd_vel (a test-side P
    controller on the ground truth within the Table 2 limits) through the lobby and along the main corridor to
    x = 15 m on the drive's own odometry; the saved map is scored against the ground truth."""
    from services.common.robot import RobotSpec

    stack = stack_factory(services=["sim", "drive", "lidar", "localization"], world="corridor", speed=3.0,
                          extra_args=["--mapping"]).start()
    node = Node("mapping-drive-test", stack.session(), stack.keys)
    spec = RobotSpec()
    state: dict = {"tf": None, "truth": None}
    node.subscribe("sim/ground_truth", lambda gt: state.__setitem__("truth", gt))
    node.subscribe("tf/map_odom", lambda tf: state.__setitem__("tf", tf))
    cmd = node.publisher("cmd_vel")
    loop = asyncio.get_running_loop()
    try:
        await wait_for(lambda: state["tf"] is not None and state["truth"] is not None, timeout_s=60,
                       message="no tf/map_odom from mapping or no ground truth")
        started = loop.time()
        for goal in MAPPING_ROUTE[1:7]:
            deadline = loop.time() + 240.0
            while True:
                p = state["truth"].pose
                dx, dy = goal[0] - p.x, goal[1] - p.y
                dth = float(wrap_angle(goal[2] - p.theta))
                if math.hypot(dx, dy) < 0.05 and abs(dth) < 0.05:
                    break
                assert loop.time() < deadline, f"goal {goal} not reached: at ({p.x:.2f}, {p.y:.2f}, {p.theta:.2f})"
                c, s = math.cos(p.theta), math.sin(p.theta)
                bx, by = c * dx + s * dy, -s * dx + c * dy  # the error in the body frame
                scale = min(1.0, (spec.vx_max_mps if bx > 0 else -spec.vx_min_mps) / max(abs(bx), 1e-9),
                            spec.vy_max_mps / max(abs(by), 1e-9))
                vx, vy, wz = spec.twist_limits().clamp(scale * bx, scale * by, 1.5 * dth)
                cmd.put(Twist2D(vx=vx, vy=vy, wz=wz))
                await asyncio.sleep(0.05)
        cmd.put(Twist2D())
        drive_s = loop.time() - started
        assert not state["truth"].collided
        saved = await node.query("localization/save_map", SaveMapRequest(name="driven"), timeout_s=10.0)
        assert saved.ok, saved.message
        agreement = map_f1(Path(saved.message), ground_truth(tmp_path))
        stats = service_stats(stack, "localization")["mapping"]
        print(f"\ndriven mapping to x = 15 m in {drive_s:.0f} s wall (sim 3x): precision {agreement.precision:.3f}, "
              f"recall {agreement.recall:.3f}, F1 {agreement.f1:.3f} at offset {agreement.offset_xy_m}; {stats}")
        assert agreement.f1 >= 0.9
    finally:
        cmd.put(Twist2D())
        node.close()
