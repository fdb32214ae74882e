"""The localization service as a real process on loopback: map serving, AMCL on odom + scans, queries, restart."""

from __future__ import annotations

import asyncio
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from proto import Keys, codec
from proto.messages import (
    Empty,
    InitialPoseRequest,
    LaserScan,
    LocalizationUpdate,
    NoMotionRequest,
    OccupancyGrid,
    Odometry,
    Pose2D,
    PoseWithCovariance,
    Reply,
    ServiceEvent,
    Transform2D,
)
from services.common.map_io import save_map
from services.common.node import Node
from services.common.se2 import compose
from services.common.session import open_session
from services.common.settings import ZenohSettings
from services.common.world import World
from services.localization.synthetic import Laser, route
from tests.support.waiting import wait_for

REPO = Path(__file__).resolve().parents[1]
MOUNT = (0.45, 0.0, 0.0)
pytestmark = pytest.mark.integration


def small_world() -> World:
    """A 12 m x 5 m room with a side bay and two boxes (enough features to localize along x)."""
    free = [[0.0, 0.0, 12.0, 5.0], [4.0, 5.0, 6.0, 6.5]]
    obstacles = [[2.0, 1.0, 2.6, 1.6], [8.0, 3.0, 9.0, 3.4]]
    return World.from_rectangles("room", 0.05, [-0.5, -0.5, 12.5, 7.0], free, obstacles)


class Service:
    def __init__(self, endpoint: str, tmp: Path, map_yaml: Path, robot_id: str, *extra: str) -> None:
        self.argv = [sys.executable, "-m", "services.localization", "--connect", endpoint, "--robot-id", robot_id,
                     "--set", f'localization.map_yaml="{map_yaml}"', "--set", f'localization.state_dir="{tmp}"',
                     "--set", "localization.save_pose_rate=5.0", *extra]
        self.proc: subprocess.Popen | None = None

    def start(self) -> Service:
        env = {**os.environ, "PYTHONPATH": str(REPO)}
        self.proc = subprocess.Popen(self.argv, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
        return self

    def stop(self) -> str:
        assert self.proc
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
        return self.proc.stdout.read().decode(errors="replace") if self.proc.stdout else ""


class Robot:
    """Publishes odom and scans of a robot driven through the world; odometry here is exact."""

    def __init__(self, node: Node, world: World) -> None:
        self.node = node
        self.laser = Laser(world, rng=np.random.default_rng(5))
        self.pub_odom = node.publisher("odom")
        self.pub_scan = node.publisher("scan")
        self.stamp = 100.0
        self.start: tuple[float, float, float] | None = None

    def odom_of(self, true):
        # odom frame = the world frame shifted so that odom starts at the origin
        sx, sy, st = self.start
        c, s = math.cos(-st), math.sin(-st)
        dx, dy = true[0] - sx, true[1] - sy
        return (c * dx - s * dy, s * dx + c * dy, true[2] - st)

    async def step(self, true) -> tuple[float, float, float]:
        if self.start is None:
            self.start = true
        self.stamp += 0.1
        o = self.odom_of(true)
        self.pub_odom.put(Odometry(stamp=self.stamp, pose=Pose2D(x=o[0], y=o[1], theta=o[2])))
        ranges = self.laser.scan(true, MOUNT)
        self.pub_scan.put(LaserScan(stamp=self.stamp, angle_min=self.laser.angle_min,
                                    angle_max=float(self.laser.angles[-1]), angle_increment=self.laser.angle_increment,
                                    range_min=0.05, range_max=20.0, ranges=ranges.astype("<f4").tobytes(),
                                    mount=Pose2D(x=MOUNT[0], y=MOUNT[1], theta=MOUNT[2])))
        await asyncio.sleep(0.02)
        return o


async def test_service_localizes_answers_queries_and_restarts_at_saved_pose(router, tmp_path):
    world = small_world()
    map_yaml, _ = save_map(world.occupancy_map(), tmp_path / "room")
    keys = Keys("loc1")
    client = Node("tester", open_session(ZenohSettings(connect=[router])), keys)
    poses: list[PoseWithCovariance] = []
    tfs: list[Transform2D] = []
    client.subscribe("pose", poses.append)
    client.subscribe("tf/map_odom", tfs.append)
    events: list[ServiceEvent] = []
    client.subscribe("localization/nomotion/_service_event", events.append)
    start = (1.0, 3.0, 0.0)
    service = Service(router, tmp_path, map_yaml, "loc1", "--set", "localization.initial_pose_x=1.0",
                      "--set", "localization.initial_pose_y=3.0").start()
    output = ""
    try:
        async def get_map():
            try:
                return await client.query("map", Empty(), timeout_s=1.0)
            except Exception:
                return None

        grid: OccupancyGrid | None = None
        for _ in range(100):
            grid = await get_map()
            if grid is not None:
                break
            await asyncio.sleep(0.1)
        assert grid is not None and (grid.width, grid.height) == (260, 150)

        robot = Robot(client, world)
        truth = list(route([start, (10.0, 2.5, 0.5)], step_m=0.05))
        for true in truth:
            odom = await robot.step(true)
        await wait_for(lambda: tfs and tfs[-1].stamp == pytest.approx(robot.stamp), timeout_s=10)
        est = compose((tfs[-1].x, tfs[-1].y, tfs[-1].theta), odom)
        assert math.hypot(est[0] - truth[-1][0], est[1] - truth[-1][1]) < 0.05
        assert poses and math.hypot(poses[-1].pose.x - truth[-1][0], poses[-1].pose.y - truth[-1][1]) < 0.1
        assert len(poses[-1].covariance) == 9 and poses[-1].covariance[0] > 0
        late: list[PoseWithCovariance] = []
        client.subscribe("pose", late.append, latched=True)  # a late joiner gets the last pose (latched)
        await wait_for(lambda: late, timeout_s=5, message="pose is not latched")
        assert late[0].pose.x == pytest.approx(poses[-1].pose.x)

        bad = await client.query("localization/initial_pose", InitialPoseRequest(pose=Pose2D(x=50.0, y=1.0)))
        assert not bad.ok and "outside the map" in bad.message
        bad = await client.query("localization/initial_pose",
                                 InitialPoseRequest(pose=Pose2D(x=1.0), covariance=[1.0, 2.0]))
        assert not bad.ok and "covariance" in bad.message
        # localization/nomotion answers once the update ran on a scan, with the pose and map->odom it published
        n = len(poses)
        asked = asyncio.ensure_future(client.query("localization/nomotion", Empty(), timeout_s=10.0))
        deadline = asyncio.get_running_loop().time() + 10.0
        while not asked.done() and asyncio.get_running_loop().time() < deadline:
            await robot.step(truth[-1])
        answer = await asked
        assert answer.ok, answer.message
        assert answer.pose is not None and answer.map_odom is not None
        await wait_for(lambda: any(p.stamp == answer.pose.stamp for p in poses[n:])
                       and any(t.stamp == answer.map_odom.stamp and t.x == answer.map_odom.x for t in tfs),
                       timeout_s=10, message="the nomotion update's pose and map->odom were not published")
        # ... and published the request and its answer as service events (what a recording replays)
        await wait_for(lambda: len(events) == 2, timeout_s=10, message="no localization/nomotion service events")
        assert [(e.event, e.sequence) for e in events] == [("request_received", 1), ("response_sent", 1)]
        assert (events[1].input_topic, events[1].input_stamp) == ("scan", answer.pose.stamp)
        assert codec.decode_as(LocalizationUpdate, events[1].response) == answer

        pose_file = tmp_path / "localization_pose.json"
        await wait_for(lambda: pose_file.is_file() and json.loads(pose_file.read_text())["x"] > 9.0, timeout_s=10)
        output = service.stop()

        # restart: the configured initial pose is (1, 3) but the saved pose wins
        tfs.clear()
        service = Service(router, tmp_path, map_yaml, "loc1", "--set", "localization.initial_pose_x=1.0",
                          "--set", "localization.initial_pose_y=3.0").start()
        robot2 = Robot(client, world)
        robot2.stamp = 500.0
        deadline = asyncio.get_running_loop().time() + 30.0  # the service starts (imports, map) meanwhile
        while not tfs and asyncio.get_running_loop().time() < deadline:
            odom = await robot2.step(truth[-1])
        assert tfs, "no map->odom after the restart"
        est = compose((tfs[-1].x, tfs[-1].y, tfs[-1].theta), odom)
        assert math.hypot(est[0] - truth[-1][0], est[1] - truth[-1][1]) < 0.15

        # an initial pose for a scan still to come (as `zagv replay` issues a recorded one) is set just before the
        # filter runs on that scan, and its service event names that scan
        pose_events: list[ServiceEvent] = []
        client.subscribe("localization/initial_pose/_service_event", pose_events.append)
        bad = await client.query("localization/initial_pose",
                                 InitialPoseRequest(pose=Pose2D(x=1.0, y=3.0), at_scan_stamp=-1.0))
        assert not bad.ok and "at_scan_stamp" in bad.message
        at_s = robot2.stamp + 0.3  # the third scan from now (its sum of 0.1 steps differs in the last bits)
        x, y, th = truth[-1]
        # (the pose is stamped on the scans' clock: this service runs on wall time, the scans here on their own)
        reply = await client.query("localization/initial_pose", InitialPoseRequest(
            pose=Pose2D(x=x, y=y, theta=th), covariance=[0.01, 0, 0, 0, 0.01, 0, 0, 0, 0.01], at_scan_stamp=at_s,
            stamp=robot2.stamp))
        assert reply.ok and "will be set on the scan" in reply.message, reply.message
        for _ in range(5):
            await robot2.step(truth[-1])
        await wait_for(lambda: [e.event for e in pose_events] == ["request_received", "response_sent"], timeout_s=10,
                       message="no initial_pose service events")
        assert (pose_events[1].input_topic, pose_events[1].input_stamp) == ("scan", pytest.approx(at_s, abs=1e-9))
        assert codec.decode_as(Reply, pose_events[1].response).ok
        # ... and so is an update at rest for a given scan
        at_s = robot2.stamp + 0.2
        asked = asyncio.ensure_future(client.query("localization/nomotion", NoMotionRequest(at_scan_stamp=at_s),
                                                   timeout_s=10.0))
        for _ in range(4):
            await robot2.step(truth[-1])
        answer = await asked
        assert answer.ok and answer.pose is not None and answer.pose.stamp == pytest.approx(at_s, abs=1e-9), answer

        reply = await client.query("localization/global", Empty())
        assert reply.ok and "particles" in reply.message
    finally:
        output += service.stop()
        client.close()
        client.session.close()
    assert "starting at the saved pose" in output, output[-3000:]


async def test_service_without_a_map_keeps_running_and_says_why(router, tmp_path):
    keys = Keys("loc2")
    client = Node("tester", open_session(ZenohSettings(connect=[router])), keys)
    service = Service(router, tmp_path, tmp_path / "missing.yaml", "loc2").start()
    try:
        reply = None
        for _ in range(100):
            try:
                reply = await client.query("localization/global", Empty(), timeout_s=1.0)
                break
            except Exception:
                await asyncio.sleep(0.1)
        assert reply is not None and not reply.ok and "missing.yaml" in reply.message
        assert service.proc.poll() is None
    finally:
        output = service.stop()
        client.close()
        client.session.close()
    assert "cannot use the map" in output
