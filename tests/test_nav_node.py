"""The nav service as a process: the test plays the robot (clock, map, odometry, map->odom, scans) on Zenoh and
drives a kinematic base with nav's cmd_vel; goals, rejections, cancel and status go through the real queries."""

from __future__ import annotations

import math
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from proto import codec
from proto import messages as m
from tests.support.waiting import wait_for_sync

pytestmark = pytest.mark.integration

RES = 0.05
REPO_ROOT = Path(__file__).resolve().parents[1]


def corridor_grid() -> m.OccupancyGrid:
    """A 10 m x 6 m grid, origin (-2, -2), free inside x in [-1.5, 7.5], y in [-1.5, 3.5]."""
    w, h = 200, 120
    occ = np.full((h, w), 100, dtype=np.int8)
    occ[10:110, 10:190] = 0
    return m.OccupancyGrid(resolution=RES, width=w, height=h, origin=m.Pose2D(x=-2.0, y=-2.0), data=occ.tobytes())


class FakeRobot:
    """Kinematic holonomic base on sim time (2x wall), publishing what drive, lidar and localization would."""

    def __init__(self, session, keys, speed: float = 2.0) -> None:
        self.session, self.keys, self.speed = session, keys, speed
        self.pose = np.zeros(3)
        self.vel = np.zeros(3)
        self.cmd = np.zeros(3)
        self.t = 0.0
        self.cmd_count = 0
        self.stop = threading.Event()
        self.grid = corridor_grid()
        grid_bytes = codec.encode(self.grid)
        self.pubs = {k: session.declare_publisher(keys(k)) for k in ("clock", "odom", "tf/map_odom", "scan", "map")}
        self.map_q = session.declare_queryable(keys("map"), lambda q: q.reply(keys("map"), grid_bytes))
        self.sub = session.declare_subscriber(keys("cmd_vel"), self._on_cmd)
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _on_cmd(self, sample) -> None:
        msg = codec.decode_as(m.Twist2D, sample.payload.to_bytes())
        self.cmd = np.array([msg.vx, msg.vy, msg.wz])
        self.cmd_count += 1

    def _run(self) -> None:
        dt = 0.01
        k = 0
        self.pubs["map"].put(codec.encode(self.grid))
        while not self.stop.is_set():
            time.sleep(dt / self.speed)
            assert np.all(np.isfinite(self.cmd))
            acc = np.array([0.5, 0.5, 1.0]) * dt
            self.vel += np.clip(self.cmd - self.vel, -acc, acc)
            c, s = math.cos(self.pose[2]), math.sin(self.pose[2])
            self.pose += dt * np.array([c * self.vel[0] - s * self.vel[1], s * self.vel[0] + c * self.vel[1],
                                        self.vel[2]])
            self.t += dt
            self.pubs["clock"].put(codec.encode(m.Clock(stamp=self.t, speed_factor=self.speed)))
            if k % 2 == 0:
                x, y, th = map(float, self.pose)
                vx, vy, wz = map(float, self.vel)
                self.pubs["odom"].put(codec.encode(m.Odometry(
                    stamp=self.t, pose=m.Pose2D(x=x, y=y, theta=th), twist=m.Twist2D(vx=vx, vy=vy, wz=wz))))
            if k % 10 == 0:
                self.pubs["tf/map_odom"].put(codec.encode(m.Transform2D(stamp=self.t)))
            if k % 4 == 0:
                ranges = np.full(541, np.inf, dtype="<f4")
                self.pubs["scan"].put(codec.encode(m.LaserScan(
                    stamp=self.t, angle_min=-3 * math.pi / 4, angle_max=3 * math.pi / 4,
                    angle_increment=math.radians(0.5), range_min=0.05, range_max=20.0, ranges=ranges.tobytes(),
                    mount=m.Pose2D(x=0.45))))
            k += 1

    def close(self) -> None:
        self.stop.set()
        self.thread.join(timeout=2)
        for p in self.pubs.values():
            p.undeclare()
        self.map_q.undeclare()
        self.sub.undeclare()


def call(session, keys, name: str, req: m.Message):
    _, rep_type = codec.query_types(name)
    replies = list(session.get(keys(name), payload=codec.encode(req), timeout=5.0))
    ok = [r.ok for r in replies if r.ok is not None]
    assert ok, f"no reply to {name}"
    return codec.decode_as(rep_type, ok[0].payload.to_bytes())


def test_goal_cancel_and_status_through_the_service(stack_factory) -> None:
    stack = stack_factory(services=["nav"]).start(wait_ready=False)  # nav is ready once it has a map and a pose
    session = stack.session()
    keys = stack.keys
    robot = FakeRobot(session, keys)
    statuses: list[m.NavStatus] = []
    sub = session.declare_subscriber(keys("nav/status"), lambda s: statuses.append(
        codec.decode_as(m.NavStatus, s.payload.to_bytes())))
    paths: list[m.Path] = []
    psub = session.declare_subscriber(keys("nav/path"), lambda s: paths.append(
        codec.decode_as(m.Path, s.payload.to_bytes())))
    robot.thread.start()
    try:
        stack.wait_line(r"^zagv: ready", timeout_s=90)
        wait_for_sync(lambda: statuses, timeout_s=20, message="no nav/status")
        wait_for_sync(lambda: robot.t > 1.0, timeout_s=10)
        # rejections name the reason
        rep = call(session, keys, "nav/goal", m.GoalRequest(pose=m.Pose2D(x=-1.9, y=0.0)))
        assert not rep.accepted and "obstacle" in rep.reason
        rep = call(session, keys, "nav/goal", m.GoalRequest(pose=m.Pose2D(x=1.0), frame="odom"))
        assert not rep.accepted and "frame" in rep.reason
        # a goal to the side and turned: reached within 2 cm / 0.02 rad of the robot's true pose
        rep = call(session, keys, "nav/goal", m.GoalRequest(pose=m.Pose2D(x=1.5, y=0.6, theta=0.8), id="g1"))
        assert rep.accepted and rep.goal_id == "g1"
        try:
            wait_for_sync(lambda: statuses[-1].goal_id == "g1" and statuses[-1].state in ("succeeded", "failed"),
                          timeout_s=90)
        except AssertionError:
            raise AssertionError(f"goal not reached: {statuses[-1]}\n{stack.output()[-3000:]}") from None
        assert statuses[-1].state == "succeeded", statuses[-1].error
        err = robot.pose - np.array([1.5, 0.6, 0.8])
        assert abs(err[0]) <= 0.02 and abs(err[1]) <= 0.02 and abs(err[2]) <= 0.02, err
        assert paths and len(codec.array(paths[-1], "poses")) > 5
        seen = {s.state for s in statuses if s.goal_id == "g1"}
        assert "driving" in seen or "rotating" in seen
        # a second goal, canceled while driving: the robot is told to stop
        rep = call(session, keys, "nav/goal", m.GoalRequest(pose=m.Pose2D(x=6.0, y=2.0, theta=0.0)))
        assert rep.accepted
        wait_for_sync(lambda: np.hypot(*robot.vel[:2]) > 0.05 or abs(robot.vel[2]) > 0.1, timeout_s=30)
        assert call(session, keys, "nav/cancel", m.CancelRequest(goal_id=rep.goal_id)).ok
        wait_for_sync(lambda: statuses[-1].state == "canceled", timeout_s=10)
        wait_for_sync(lambda: np.allclose(robot.cmd, 0.0), timeout_s=10)
        assert not call(session, keys, "nav/cancel", m.CancelRequest()).ok
        assert call(session, keys, "nav/clear_costmaps", m.Empty()).ok
        # the zagv goal command follows a goal to its end
        cli = [sys.executable, "-m", "services.cli", "goal", "--connect", stack.endpoint, "--robot-id",
               stack.robot_id]
        done = subprocess.run([*cli, "1.0", "1.0", "0.0"], capture_output=True, text=True, timeout=120,
                              cwd=REPO_ROOT)
        assert done.returncode == 0, done.stdout + done.stderr
        assert "accepted as" in done.stdout and "succeeded" in done.stdout
        rejected = subprocess.run([*cli, "--", "-1.9", "0", "0"], capture_output=True, text=True, timeout=60,
                                  cwd=REPO_ROOT)
        assert rejected.returncode == 1 and "rejected" in rejected.stdout
    finally:
        sub.undeclare()
        psub.undeclare()
        robot.close()
