"""The scenario runner's view of a running stack: a Zenoh client that follows the clock, ground truth, odometry,
localization, nav and the map, and records each leg (``Leg``) for the report; ``wait_until`` for start-up."""

from __future__ import annotations

import asyncio
import contextlib
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from proto import codec
from proto import messages as m
from proto.keys import Keys
from services.common.query import query
from services.common.se2 import compose
from services.scenario.model import Goal


@dataclass
class Leg:
    run: int
    goal: Goal
    start_t: float
    plan: np.ndarray | None = None
    final_plan: np.ndarray | None = None
    obstacles: list[tuple[float, float, float, float]] = field(default_factory=list)
    trace: list[tuple[float, float, float, float, float, float, float]] = field(default_factory=list)
    #: the pose nav drives on (map->odom composed with odometry) at every odometry stamp of the leg: (t, x, y)
    estimates: list[tuple[float, float, float]] = field(default_factory=list)


def localization_errors_m(leg: Leg) -> np.ndarray:
    """|estimate - ground truth| (m) at each estimate's stamp, the truth interpolated between its samples there
    (matched in sim time, so the lag of the messages under load is not counted as error)."""
    tr = np.asarray(leg.trace, dtype=float).reshape(-1, 7)
    est = np.asarray(leg.estimates, dtype=float).reshape(-1, 3)
    if len(tr) < 2 or not len(est):
        return np.zeros(0)
    order = np.argsort(tr[:, 0], kind="stable")
    t, x, y = tr[order, 0], tr[order, 1], tr[order, 2]
    inside = (est[:, 0] >= t[0]) & (est[:, 0] <= t[-1])
    e = est[inside]
    return np.hypot(e[:, 1] - np.interp(e[:, 0], t, x), e[:, 2] - np.interp(e[:, 0], t, y))


def _passes_around(poses: np.ndarray, rects: list[tuple[float, float, float, float]], near_m: float = 1.5) -> bool:
    """Whether a path comes within ``near_m`` of an obstacle but keeps 0.6 m off it (a detour, not a stop)."""
    for x0, y0, x1, y1 in rects:
        dx = np.maximum(np.maximum(x0 - poses[:, 0], poses[:, 0] - x1), 0.0)
        dy = np.maximum(np.maximum(y0 - poses[:, 1], poses[:, 1] - y1), 0.0)
        d = np.hypot(dx, dy)
        if d.min() < near_m and d.min() > 0.6:
            return True
    return False


class Client:
    """What the runner watches: sim clock, ground truth, nav status and path."""

    def __init__(self, session, keys: Keys, loop: asyncio.AbstractEventLoop) -> None:
        self.session, self.keys, self.loop = session, keys, loop
        self.sim_time = 0.0
        self.truth: m.GroundTruth | None = None
        self.status: m.NavStatus | None = None
        self.status_changed = asyncio.Event()
        self.paths: list[tuple[float, np.ndarray]] = []
        self.odom_count = 0
        self.pose: m.PoseWithCovariance | None = None
        self.pose_count = 0
        self.odom: tuple[float, float, float] | None = None
        self.map_odom: tuple[float, float, float] | None = None
        self.collisions = 0
        self.leg: Leg | None = None
        self.jogging = False  # the mapping phase drives the robot (collisions count then too)
        self.truth_changed = asyncio.Event()
        self.aborted = False
        self.detours: list[bool] = []  # per leg with a dynamic obstacle: whether nav planned around it
        self.localization_errors: list[tuple[float, float, float]] = []
        self._subs: list[Any] = []
        self._sub("clock", m.Clock, self._on_clock)
        self._sub("sim/ground_truth", m.GroundTruth, self._on_truth)
        self._sub("nav/status", m.NavStatus, self._on_status)
        self._sub("nav/path", m.Path, self._on_path)
        self._sub("odom", m.Odometry, self._on_odom)
        self._sub("pose", m.PoseWithCovariance, self._on_pose)
        self._sub("tf/map_odom", m.Transform2D, self._on_tf)

    def _on_odom(self, msg: m.Odometry) -> None:
        self.odom_count += 1
        self.odom = (msg.pose.x, msg.pose.y, msg.pose.theta)
        est = self.estimate()
        if self.leg is not None and est is not None:
            self.leg.estimates.append((msg.stamp, est[0], est[1]))

    def _on_tf(self, msg: m.Transform2D) -> None:
        self.map_odom = (msg.x, msg.y, msg.theta)

    def estimate(self) -> tuple[float, float, float] | None:
        """The robot's pose as nav sees it: map->odom composed with the odometry pose."""
        if self.odom is None or self.map_odom is None:
            return None
        return compose(self.map_odom, self.odom)

    def _on_pose(self, msg: m.PoseWithCovariance) -> None:
        self.pose = msg
        self.pose_count += 1

    def _sub(self, name: str, t: type, cb) -> None:
        def on_sample(sample) -> None:
            try:
                msg: Any = codec.decode_as(t, sample.payload.to_bytes(), str(sample.key_expr))
            except codec.ProtoDecodeError:
                return
            with contextlib.suppress(RuntimeError):  # the loop already closed at the end of the run
                self.loop.call_soon_threadsafe(cb, msg)

        self._subs.append(self.session.declare_subscriber(self.keys(name), on_sample))

    def _on_clock(self, msg: m.Clock) -> None:
        self.sim_time = max(self.sim_time, msg.stamp)

    def _on_truth(self, msg: m.GroundTruth) -> None:
        if msg.collided and not (self.truth and self.truth.collided) and (self.leg is not None or self.jogging):
            self.collisions += 1  # while driving a leg (the sim's own start pose may lie in a wall of a map)
        self.truth = msg
        self.sim_time = max(self.sim_time, msg.stamp)
        if self.leg is not None:
            p, v = msg.pose, msg.twist
            self.leg.trace.append((msg.stamp, p.x, p.y, p.theta, v.vx, v.vy, v.wz))
        self.truth_changed.set()

    def _on_status(self, msg: m.NavStatus) -> None:
        self.status = msg
        self.status_changed.set()

    def _on_path(self, msg: m.Path) -> None:
        poses = codec.array(msg, "poses").copy()
        leg = self.leg
        if leg is not None and len(poses):
            if leg.plan is None:
                leg.plan = poses
            elif leg.obstacles and leg.final_plan is None and _passes_around(poses, leg.obstacles):
                leg.final_plan = poses

    async def query(self, name: str, req: m.Message | None = None, timeout_s: float = 5.0) -> Any:
        return await query(self.session, self.keys, name, req, timeout_s=timeout_s)

    async def sim_sleep(self, dt: float) -> None:
        end = self.sim_time + dt
        while self.sim_time < end:
            await asyncio.sleep(0.02)

    def close(self) -> None:
        for s in self._subs:
            with contextlib.suppress(Exception):
                s.undeclare()


async def wait_until(cond, what: str, timeout_s: float) -> None:
    """Wait (wall time) for ``cond()``; RuntimeError naming ``what`` after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            raise RuntimeError(f"{what} within {timeout_s:.0f} s")
        await asyncio.sleep(0.05)
