"""The hmi_api's link to the robot: Zenoh subscriptions, queries, the jog publisher, login and the pose database.

Everything here runs on the service's event loop; SQLite calls run on one worker thread (so a commit's fsync
never stalls the loop) and scrypt runs in the default executor.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import logging
import math
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal, TypeVar

import msgspec
import zenoh

from proto.messages import (
    CancelRequest,
    Empty,
    GoalReply,
    GoalRequest,
    InitialPoseRequest,
    ModeRequest,
    OccupancyGrid,
    Pose2D,
    Reply,
    SaveMapRequest,
    Twist2D,
    Waypoint,
    WaypointsRequest,
)
from services.common import auth
from services.common.clock import Rate
from services.common.grid import grid_png
from services.common.node import Node
from services.common.query import QueryError
from services.common.robot import RobotSpec
from services.hmi_api.config import HmiApiConfig
from services.hmi_api.jog import JogGate
from services.hmi_api.posedb import DB_FILE, PoseDb, PoseRecord
from services.hmi_api.view import RobotView, VelocityRecorder

T = TypeVar("T")
log = logging.getLogger("zagv.hmi_api")

ACTIVE_NAV_STATES = {"planning", "driving", "rotating", "recovering"}


class RobotUnavailable(RuntimeError):
    """A robot service did not answer a query (not running, or too slow)."""


class RobotRejected(RuntimeError):
    """A robot service answered with a refusal; the message is its reason."""


async def _first_of(*events: asyncio.Event) -> None:
    """Return once any of ``events`` is set."""
    waiters = [asyncio.ensure_future(e.wait()) for e in events]
    try:
        await asyncio.wait(waiters, return_when=asyncio.FIRST_COMPLETED)
    finally:
        for w in waiters:
            w.cancel()


class Backend:
    """State and actions behind the HTTP API (one per process)."""

    def __init__(self, node: Node, robot: RobotSpec, config: HmiApiConfig) -> None:
        self.node = node
        self.robot = robot
        self.config = config
        self.view = RobotView()
        self.jog = JogGate(timeout_s=config.jog_timeout_s)
        self.recorder = VelocityRecorder(config.velocity_history_s, config.velocity_record_hz)
        self.state_dir = Path(config.state_dir).expanduser()
        self.state_dir.mkdir(parents=True, exist_ok=True)
        self._db_thread = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix="posedb")
        self.db = PoseDb(self.state_dir / DB_FILE, max_poses=config.max_poses)
        self.password_login = auth.PasswordLogin(
            self._load_password(), token_ttl_s=config.token_ttl_s, free_attempts=config.login_free_attempts,
            lockout_initial_s=config.login_lockout_initial_s, lockout_max_s=config.login_lockout_max_s, log=log)
        self.tokens = self.password_login.tokens
        self._cmd_at_s = -math.inf
        self._map_png: tuple[int, bytes] | None = None
        self._cmd_pub = node.publisher("cmd_vel")
        self.jog_published = 0
        self._jog_requested = asyncio.Event()  # set by each jog request: wakes a silent jog loop
        self._subscribe()
        self._health_sub = node.session.liveliness().declare_subscriber(
            node.keys.health_all, self._on_health, history=True)

    # ------------------------------------------------------------------ setup

    def _load_password(self) -> str:
        if self.config.password_hash:
            auth.check_hash_format(self.config.password_hash, "hmi_api.password_hash")
            return self.config.password_hash
        stored, password = auth.first_run_hash(self.state_dir)
        if password is not None:
            # shown once: the launcher prints service output, so `zagv up --sim` shows this line
            print(f"zagv hmi: first-run password: {password}", flush=True)
            log.info("first-run password stored (hashed) in %s", self.state_dir / auth.FIRST_RUN_FILE)
        else:
            log.info("login with the first-run password stored in %s", self.state_dir / auth.FIRST_RUN_FILE)
        return stored

    def _subscribe(self) -> None:
        v = self.view
        n = self.node

        def setter(attr: str, version: str | None = None) -> Callable[[Any], None]:
            def set_it(msg: Any) -> None:
                setattr(v, attr, msg)
                v.received[attr] = time.monotonic()
                if version:
                    setattr(v, version, getattr(v, version) + 1)
            return set_it

        # latched topics (pose, map_odom, nav/status, paths, map) arrive whatever the start order (Node.subscribe).
        # Every handler only stores the newest message, which the paced WebSocket frames and the HTTP handlers read:
        # they run on the subscribers' reader threads (an attribute store is atomic under the GIL), so the
        # 190 messages a second the HMI watches do not wake its event loop once each.
        newest: dict[str, Any] = {"on_zenoh_thread": True, "queue": 1}
        n.subscribe("odom", setter("odom"), **newest)
        n.subscribe("pose", setter("pose"), latched=True, **newest)
        n.subscribe("tf/map_odom", setter("map_odom"), latched=True, **newest)
        n.subscribe("wheels", setter("wheels"), **newest)
        n.subscribe("nav/status", setter("nav"), latched=True, **newest)
        n.subscribe("safety/state", setter("safety"), latched=True, **newest)
        n.subscribe("scan", setter("scan"), **newest)
        n.subscribe("nav/path", setter("path", "path_version"), latched=True, **newest)
        n.subscribe("nav/local_plan", setter("local_plan", "path_version"), **newest)
        n.subscribe("particles", setter("particles", "particles_version"), **newest)
        n.subscribe("map", self._on_map, latched=True, **newest)
        n.subscribe("cmd_vel", self._on_cmd, **newest)

    def _on_map(self, grid: OccupancyGrid) -> None:
        self.view.grid = grid
        self.view.map_version += 1

    def _on_cmd(self, cmd: Twist2D) -> None:
        self.view.cmd = cmd
        self._cmd_at_s = self.node.clock.now()

    def _on_health(self, sample: zenoh.Sample) -> None:
        name = str(sample.key_expr).rsplit("/", 1)[-1]
        up = sample.kind == zenoh.SampleKind.PUT

        def update() -> None:
            (self.view.alive.add if up else self.view.alive.discard)(name)
        self.node.loop.call_soon_threadsafe(update)

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self._health_sub.undeclare()
        self._db_thread.shutdown(wait=True)
        self.db.close()

    # ------------------------------------------------------------------ loops

    async def jog_loop(self, stop: asyncio.Event) -> None:
        """Publish the jog twist at ``jog_rate_hz`` on the robot clock while the dead-man allows it.

        The dead-man itself uses wall time (time.monotonic): it watches the browser's link, which lives in real
        time whatever the simulator's speed.
        """
        rate = Rate(self.node.clock, self.config.jog_rate_hz)
        while not stop.is_set():
            out = self.jog.next_output(time.monotonic())
            if out is None:  # silent until the next jog request: no wake-up per cycle while nobody jogs
                self._jog_requested.clear()
                await _first_of(self._jog_requested, stop)
                rate = Rate(self.node.clock, self.config.jog_rate_hz)
                continue
            self._cmd_pub.put(Twist2D(vx=out[0], vy=out[1], wz=out[2], stamp=self.node.clock.now()))
            self.jog_published += 1
            await rate.sleep()

    async def record_loop(self, stop: asyncio.Event) -> None:
        """Sample commanded and measured velocities at ``velocity_record_hz`` on the robot clock."""
        rate = Rate(self.node.clock, self.config.velocity_record_hz)
        while not stop.is_set():
            self.recorder.sample(self.node.clock.now(), self.view.cmd, self._cmd_at_s, self.view.odom)
            await rate.sleep()

    # ------------------------------------------------------------------ login

    async def login(self, password: str, client: str) -> str | None:
        """A token for the right password, None for a wrong one; LoginThrottled while ``client`` is locked out."""
        return await self.password_login.login(password, client)

    # ------------------------------------------------------------------ database

    async def db_call(self, fn: Callable[..., T], *args: Any, **kwargs: Any) -> T:
        """Run a PoseDb method on the database thread; returns after its transaction committed."""
        loop = asyncio.get_running_loop()
        return await loop.run_in_executor(self._db_thread, lambda: fn(*args, **kwargs))

    # ------------------------------------------------------------------ robot actions

    async def query(self, name: str, request: Any, timeout_s: float | None = None) -> Any:
        """``name`` asked within ``timeout_s`` (default ``query_timeout_s``); RobotUnavailable when unanswered."""
        try:
            return await self.node.query(name, request, timeout_s=timeout_s or self.config.query_timeout_s)
        except QueryError as exc:
            raise RobotUnavailable(f"{name}: {exc}") from None

    async def reply_query(self, name: str, request: Any = None, timeout_s: float | None = None) -> Reply:
        reply: Reply = await self.query(name, request if request is not None else Empty(), timeout_s)
        if not reply.ok:
            raise RobotRejected(f"{name} refused: {reply.message or 'no reason given'}")
        return reply

    async def drive(self, action: str) -> Reply:
        if action in ("estop", "disable"):
            self.jog.stop()
        return await self.reply_query(f"drive/{action}")

    async def estop(self) -> Reply:
        """E-stop the drive and end any jog; navigation is canceled in the background (nav may be absent, and an
        e-stop answer must not wait for it)."""
        self.jog.stop()
        self.node.spawn(self._cancel_quietly())
        return await self.reply_query("drive/estop")

    def jog_command(self, vx: float, vy: float, wz: float) -> tuple[float, float, float]:
        twist = self.robot.twist_limits().clamp(vx, vy, wz)
        started = self.jog.command(twist, time.monotonic())
        self._jog_requested.set()
        nav = self.view.nav
        if started and nav is not None and nav.state in ACTIVE_NAV_STATES:
            # a jog takes the robot from navigation: cancel the goal so nav stops commanding too
            self.node.spawn(self._cancel_quietly())
        return twist

    async def _cancel_quietly(self) -> None:
        try:
            await self.query("nav/cancel", CancelRequest())
        except RobotUnavailable as exc:
            log.warning("could not cancel navigation: %s", exc)

    async def goal(self, x: float, y: float, theta: float, goal_id: str = "") -> GoalReply:
        reply: GoalReply = await self.query("nav/goal", GoalRequest(pose=Pose2D(x=x, y=y, theta=theta), id=goal_id))
        if not reply.accepted:
            raise RobotRejected(f"nav/goal refused: {reply.reason or 'no reason given'}")
        return reply

    async def cancel(self) -> Reply:
        """Cancel whatever goal or sequence nav is running."""
        return await self.reply_query("nav/cancel", CancelRequest())

    async def initial_pose(self, x: float, y: float, theta: float) -> Reply:
        return await self.reply_query("localization/initial_pose",
                                      InitialPoseRequest(pose=Pose2D(x=x, y=y, theta=theta)))

    async def mapping_mode(self, mode: Literal["mapping", "navigation"], map_yaml: str = "") -> Reply:
        """``localization/mode``: ``mapping`` (a new map) or ``navigation`` on ``map_yaml``."""
        return await self.reply_query("localization/mode", ModeRequest(mode=mode, map_yaml=map_yaml))

    async def save_map(self, name: str) -> Reply:
        """``localization/save_map``; the reply's message is the saved YAML's path on the robot."""
        return await self.reply_query("localization/save_map", SaveMapRequest(name=name))

    async def send_pose(self, pose: PoseRecord) -> GoalReply:
        return await self.goal(pose.x, pose.y, pose.theta, f"pose{pose.id}-{uuid.uuid4().hex[:6]}")

    async def run_poses(self, poses: list[PoseRecord]) -> GoalReply:
        if not poses:
            raise RobotRejected("the pose list is empty")
        request = WaypointsRequest(waypoints=[Waypoint(pose=Pose2D(x=p.x, y=p.y, theta=p.theta), id=f"pose{p.id}")
                                              for p in poses], id=f"run-{uuid.uuid4().hex[:6]}")
        reply: GoalReply = await self.query("nav/waypoints", request)
        if not reply.accepted:
            raise RobotRejected(f"nav/waypoints refused: {reply.reason or 'no reason given'}")
        return reply

    # ------------------------------------------------------------------ views

    def status(self) -> dict:
        active = self.jog.active(time.monotonic())
        vx, vy, wz = self.jog.current() if active else (0.0, 0.0, 0.0)
        jog = {"active": active, "vx": vx, "vy": vy, "wz": wz}
        clock = "sim" if self.node.clock.is_sim else "wall"
        return self.view.status(self.node.clock.now(), clock, jog, time.monotonic())

    def map_png(self) -> bytes | None:
        grid = self.view.grid
        if grid is None:
            return None
        if self._map_png is None or self._map_png[0] != self.view.map_version:
            self._map_png = (self.view.map_version, grid_png(grid))
        return self._map_png[1]

    def map_meta(self) -> dict:
        grid = self.view.grid
        if grid is None:
            return {"available": False, "version": 0}
        return {"available": True, "version": self.view.map_version, "frame": grid.frame,
                "width": grid.width, "height": grid.height, "resolution_m": grid.resolution,
                "origin": {"x": grid.origin.x, "y": grid.origin.y, "theta": grid.origin.theta}}

    def frame(self, full: bool, last_versions: tuple[int, int]) -> tuple[bytes, tuple[int, int]]:
        """One WebSocket frame (JSON): status, scan and velocity sample always; paths and particles when they
        changed since ``last_versions`` or when ``full``."""
        v = self.view
        out: dict[str, Any] = {"type": "tick", "status": self.status(),
                               "scan": v.scan_points(self.config.scan_max_points)}
        if self.recorder.rows:
            out["vel"] = list(self.recorder.rows[-1])
        if full or v.path_version != last_versions[0]:
            out["paths"] = {"global": v.path_list(v.path), "local": v.path_list(v.local_plan)}
        if full or v.particles_version != last_versions[1]:
            out["particles"] = v.particle_list(self.config.particles_max)
        return msgspec.json.encode(out), (v.path_version, v.particles_version)
