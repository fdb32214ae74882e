"""SIGKILL of each service during a navigation goal (sim, drive, lidar, localization, nav under ``zagv up``).

Every killed service is restarted by the supervisor. The robot never drives blind: without fresh scans or poses it
stops (ground-truth speed ~0) within the pose timeout and the deceleration, or nav reports the goal failed or
recovering; afterwards the goal resumes or ends with a reason. Killing nav stops the robot through the drive's
cmd_vel timeout; killing drive stops it through the motor controllers' watchdog.
"""

from __future__ import annotations

import contextlib
import math
import os
import signal
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from proto import codec
from proto.messages import (
    CancelRequest,
    Empty,
    GoalReply,
    GoalRequest,
    GroundTruth,
    InitialPoseRequest,
    LocalizationUpdate,
    NavStatus,
    Pose2D,
    PoseWithCovariance,
    Reply,
    TeleportRequest,
)
from proto.registry import TOPICS
from services.launch.stack_process import Stack
from tests.support.waiting import wait_for_sync

pytestmark = [pytest.mark.integration, pytest.mark.slow]

SERVICES = ["sim", "drive", "lidar", "localization", "nav"]
START = (1.0, 3.2, 0.0)  # corridor world
EAST, WEST = (12.0, 3.2, 0.0), (2.0, 3.2, math.pi)
STILL_MPS = 0.01
POSE_TIMEOUT_S = 2.0  # nav.pose_timeout_s (sim s)
SPEED = 1.0


class Navigator:
    """Goals in, ``nav/status`` and ``sim/ground_truth`` (with its sim stamps) out."""

    def __init__(self, stack: Stack) -> None:
        self.stack = stack
        self.session = stack.session()
        self.lock = threading.Lock()
        self.status: NavStatus | None = None
        self.status_log: list[NavStatus] = []
        self.truth: GroundTruth | None = None
        self.truth_log: list[GroundTruth] = []
        self.pose: PoseWithCovariance | None = None
        self.pose_log: list[PoseWithCovariance] = []
        self.session.declare_subscriber(stack.keys("pose"), self._on(PoseWithCovariance, "pose"))
        self.session.declare_subscriber(stack.keys("nav/status"), self._on(NavStatus, "status"))
        self.session.declare_subscriber(stack.keys("sim/ground_truth"), self._on(GroundTruth, "truth"))

    def _on(self, t: type, attr: str):
        def cb(sample) -> None:
            msg = codec.decode_as(t, sample.payload.to_bytes())
            with self.lock:
                setattr(self, attr, msg)
                getattr(self, f"{attr}_log").append(msg)
        return cb

    def query(self, name: str, request, reply_type: type):
        """The reply to ``name``; asked again while nobody answers (a fresh service's health token comes up before
        its queryables)."""
        key = self.stack.keys(name)
        payload = codec.encode(request)

        def answered() -> list:
            return [r for r in self.session.get(key, payload=payload, timeout=5.0) if r.ok is not None]

        replies = wait_for_sync(answered, timeout_s=30, poll_s=0.2, message=f"{name} never answered")
        return codec.decode_as(reply_type, replies[0].ok.payload.to_bytes())

    def wait_sim(self, sim_t: float) -> None:
        wait_for_sync(lambda: self.truth.stamp >= sim_t, timeout_s=(sim_t - self.truth.stamp) / SPEED * 4 + 10)

    def speed(self) -> float:
        t = self.truth.twist
        return math.hypot(t.vx, t.vy)

    def place(self, pose: tuple[float, float, float]) -> None:
        p = Pose2D(x=pose[0], y=pose[1], theta=pose[2])
        assert self.query("sim/teleport", TeleportRequest(pose=p), Reply).ok
        cov = [0.0025, 0, 0, 0, 0.0025, 0, 0, 0, 0.003]
        wait_for_sync(lambda: math.hypot(self.truth.pose.x - pose[0], self.truth.pose.y - pose[1]) < 0.01,
                      timeout_s=10, message="the teleport never showed in sim/ground_truth")
        for _ in range(6):
            assert self.query("localization/initial_pose", InitialPoseRequest(pose=p, covariance=cov), Reply).ok
            count = len(self.pose_log)

            def localized() -> bool:
                e = self.pose
                return len(self.pose_log) > count and math.hypot(e.pose.x - pose[0], e.pose.y - pose[1]) < 0.1  # noqa: B023

            try:
                wait_for_sync(localized, timeout_s=10)
                return
            except AssertionError:
                continue
        raise AssertionError(f"localization never reported a pose near {pose}")

    def goal(self, pose: tuple[float, float, float], goal_id: str) -> None:
        request = GoalRequest(pose=Pose2D(x=pose[0], y=pose[1], theta=pose[2]), id=goal_id)

        def accepted() -> bool:
            reply = self.query("nav/goal", request, GoalReply)
            if not reply.accepted and "no robot pose" in reply.reason:
                # a restarted nav has no pose until localization publishes one, which it does after motion or
                # on this request (nav does not fetch localization's latched pose when it starts)
                self.query("localization/nomotion", Empty(), LocalizationUpdate)
                return False
            assert reply.accepted, reply.reason
            return True

        wait_for_sync(accepted, timeout_s=30, poll_s=0.5, message="nav never had a robot pose for the goal")
        wait_for_sync(lambda: self.status and self.status.goal_id == goal_id and self.status.state == "driving"
                      and self.speed() > 0.1, timeout_s=60, message=f"goal {goal_id} never got going: {self.status}")


@contextlib.contextmanager
def navigator(run_dir: Path, extra_args: list[str]) -> Iterator[Navigator]:
    stack = Stack(run_dir, SERVICES, world="corridor", speed=SPEED, extra_args=extra_args)
    try:
        stack.start()
        n = Navigator(stack)
        wait_for_sync(lambda: n.truth is not None and n.status is not None, timeout_s=60)
        n.place(START)
        yield n
    finally:
        stack.stop()


@pytest.fixture(scope="module")
def nav(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Navigator]:
    """Each service in a process of its own (``--no-compose``), so that each can be killed alone."""
    with navigator(tmp_path_factory.mktemp("nav_faults"), ["--no-compose"]) as n:
        yield n


#: per killed service: the data it produces (None: none to wait for) and the sim s within which the robot must be
#: still unless a new instance delivers that data: nav's pose timeout for sensor data, the drive's cmd_vel timeout
#: for nav, the motor controllers' watchdog (1 s) for drive (a quick new drive may take over before the wheels
#: stop: then its wheel states are back in time); plus 0.7 s deceleration and clock slack
BOUNDS = {
    "lidar": ("scan", POSE_TIMEOUT_S + 0.7 + 0.5),
    "localization": ("tf/map_odom", POSE_TIMEOUT_S + 0.7 + 0.5),
    "nav": (None, 0.2 + 0.7 + 0.5),
    "drive": ("wheels", 1.0 + 0.7 + 0.5),
}


@pytest.mark.parametrize("service", list(BOUNDS))
def test_sigkill_during_goal_never_drives_blind(nav: Navigator, service: str, fault_figures) -> None:
    n = nav
    target = EAST if n.truth.pose.x < 7.0 else WEST
    goal_id = f"kill-{service}"
    n.goal(target, goal_id)
    stack = n.stack
    produces, bound_s = BOUNDS[service]
    stamps: list[float] = []
    if produces:
        sub = n.session.declare_subscriber(stack.keys(produces), lambda s: stamps.append(
            codec.decode_as(TOPICS[produces], s.payload.to_bytes()).stamp))
    mark = stack.line_count()
    with n.lock:
        first_truth = len(n.truth_log)
        killed_sim = n.truth.stamp
    killed = time.monotonic()
    os.kill(stack.pid(service), signal.SIGKILL)
    n.wait_sim(killed_sim + bound_s + 0.5)
    with n.lock:
        stops = [g.stamp for g in n.truth_log[first_truth:] if math.hypot(g.twist.vx, g.twist.vy) < STILL_MPS]
    stopped = stops[0] - killed_sim if stops else math.inf
    fresh = [t for t in stamps if t > killed_sim + 0.1]  # later than anything the killed process had in flight
    data_gap = fresh[0] - killed_sim if fresh else math.inf
    if produces:
        sub.undeclare()
        fault_figures(f"{service}_killed_{produces.replace('/', '_')}_gap_sim", data_gap)
    if stops:
        fault_figures(f"{service}_killed_to_standstill_sim", stopped)
    assert stopped <= bound_s or data_gap <= bound_s, (
        f"after killing {service} the robot drove on for {bound_s} sim s without fresh {produces or 'commands'}")

    stack.wait_line(rf"^zagv: {service} healthy again", timeout_s=60, after=mark)
    fault_figures(f"{service}_killed_during_goal_to_healthy_wall", time.monotonic() - killed)
    if service == "drive":
        # a restarted drive comes back disabled: nav's commands must not move the robot until an explicit enable
        with n.lock:
            back_sim = n.truth.stamp
            first_back = len(n.truth_log)
        n.wait_sim(back_sim + 2.0)
        with n.lock:
            moved = [g.stamp for g in n.truth_log[first_back:] if math.hypot(g.twist.vx, g.twist.vy) > 0.01]
        assert not moved, f"the restarted drive moved the robot at sim {moved[0]:.2f} s without an enable"
        assert n.query("drive/enable", Empty(), Reply).ok

    def settled() -> str:
        st = n.status
        if service == "nav":  # the goal died with nav: the new instance is idle and commands nothing
            return "idle" if st.state == "idle" and n.speed() < STILL_MPS else ""
        if st.goal_id != goal_id:
            return ""
        if st.state == "succeeded" or (st.state == "driving" and n.speed() > 0.05):
            return st.state
        if st.state == "failed" and st.error:
            return f"failed: {st.error}"
        return ""

    outcome = wait_for_sync(settled, timeout_s=90, message=f"after {service} came back: {n.status}")
    print(f"\n{service} killed during goal {goal_id}: {outcome}")
    # leave the robot at rest for the next case
    if n.status.state not in ("succeeded", "failed", "canceled", "idle"):
        assert n.query("nav/cancel", CancelRequest(goal_id=goal_id), Reply).ok
    wait_for_sync(lambda: n.speed() < STILL_MPS, timeout_s=30)


@pytest.mark.parametrize("service", ["lidar", "localization"])
def test_hung_sensor_during_goal_stops_the_robot(nav: Navigator, service: str) -> None:
    """A frozen lidar or localization (SIGSTOP: no restart, no fresh data for 5 sim s) must stop the robot."""
    n = nav
    target = EAST if n.truth.pose.x < 7.0 else WEST
    goal_id = f"hang-{service}"
    n.goal(target, goal_id)
    pid = n.stack.pid(service)
    with n.lock:
        first_truth = len(n.truth_log)
        frozen_sim = n.truth.stamp
    os.kill(pid, signal.SIGSTOP)
    try:
        n.wait_sim(frozen_sim + 5.0)
    finally:
        os.kill(pid, signal.SIGCONT)
    try:
        with n.lock:
            late = [math.hypot(g.twist.vx, g.twist.vy) for g in n.truth_log[first_truth:]
                    if g.stamp > frozen_sim + POSE_TIMEOUT_S + 0.7 + 0.5]
        assert late and max(late) < STILL_MPS, f"drove on at up to {max(late):.2f} m/s without fresh {service} data"
    finally:
        if n.status.state not in ("succeeded", "failed", "canceled", "idle"):
            n.query("nav/cancel", CancelRequest(goal_id=goal_id), Reply)
        wait_for_sync(lambda: n.speed() < STILL_MPS, timeout_s=30)


def test_sigkill_of_the_composed_process_during_goal_stops_the_robot(tmp_path: Path, fault_figures) -> None:
    """zagv up's default: lidar, localization and nav share ``components``. Killing it kills all three at once: the
    drive's cmd_vel timeout stops the robot, the supervisor restarts the process, every service in it is healthy
    again, and the new nav is idle, commanding nothing."""
    with navigator(tmp_path, []) as n:
        stack = n.stack
        assert {stack.process_of(s) for s in ("lidar", "localization", "nav")} == {"components"}
        n.goal(EAST, "kill-components")
        mark = stack.line_count()
        with n.lock:
            first_truth = len(n.truth_log)
            killed_sim = n.truth.stamp
        killed = time.monotonic()
        os.kill(stack.pid("components"), signal.SIGKILL)
        bound_s = BOUNDS["nav"][1]
        n.wait_sim(killed_sim + bound_s + 0.5)
        with n.lock:
            stops = [g.stamp for g in n.truth_log[first_truth:] if math.hypot(g.twist.vx, g.twist.vy) < STILL_MPS]
        assert stops and stops[0] - killed_sim <= bound_s, "the robot drove on after its composed services died"
        fault_figures("components_killed_to_standstill_sim", stops[0] - killed_sim)
        for service in ("lidar", "localization", "nav"):
            stack.wait_line(rf"^zagv: {service} healthy again", timeout_s=60, after=mark)
        fault_figures("components_killed_during_goal_to_healthy_wall", time.monotonic() - killed)
        wait_for_sync(lambda: n.status.state == "idle" and n.speed() < STILL_MPS, timeout_s=60,
                      message=f"after components came back: {n.status}")
