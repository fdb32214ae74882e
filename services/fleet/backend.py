"""The fleet view's link to the robots: wildcard subscriptions over every ``agv/<id>/``, presence by health tokens,
the per-robot queries the site may send (goal, pose list, cancel, e-stop) and the login.

Samples are decoded on Zenoh's threads and handed to the event loop; the FleetView core is only touched there.
"""

from __future__ import annotations

import contextlib
import logging
import time
import uuid
from typing import Any

import zenoh

from proto import codec
from proto.keys import HEALTH, ROOT, Keys, split_key
from proto.messages import (
    CancelRequest,
    Empty,
    GoalReply,
    GoalRequest,
    Pose2D,
    Reply,
    Waypoint,
    WaypointsRequest,
)
from services.common import auth
from services.common.grid import grid_png
from services.common.node import Node
from services.common.query import QueryError, query
from services.common.robot import RobotSpec
from services.fleet.config import FleetConfig
from services.fleet.core import LATCHED, TOPICS, FleetView

log = logging.getLogger("zagv.fleet")


class RobotUnavailable(RuntimeError):
    """The robot is not at the site, or did not answer."""


class RobotRejected(RuntimeError):
    """The robot answered with a refusal; the message is its reason."""


class UnknownRobot(LookupError):
    """No robot of that id has been heard at the site."""


class FleetBackend:
    """State and actions behind the fleet view's HTTP API (one per process)."""

    def __init__(self, node: Node, robot: RobotSpec, config: FleetConfig) -> None:
        self.node = node
        self.robot = robot
        self.config = config
        self.view = FleetView(own_id=node.keys.robot_id, robots_shown=list(config.robots), map_from=config.map_from)
        self.password_login = auth.PasswordLogin(
            self._load_password(), token_ttl_s=config.token_ttl_s, free_attempts=config.login_free_attempts,
            lockout_initial_s=config.login_lockout_initial_s, lockout_max_s=config.login_lockout_max_s, log=log)
        self.tokens = self.password_login.tokens
        self._map_png: tuple[int, bytes] | None = None
        session = node.session
        self._declared: list[Any] = [session.declare_subscriber(f"{ROOT}/*/{topic}", self._sample_handler(topic))
                                     for topic in TOPICS]
        self._declared.append(session.liveliness().declare_subscriber(f"{ROOT}/*/{HEALTH}/*", self._on_health,
                                                                      history=True))

    def _load_password(self) -> str:
        from pathlib import Path

        if self.config.password_hash:
            return self.config.password_hash
        state_dir = Path(self.config.state_dir).expanduser()
        stored, password = auth.first_run_hash(state_dir)
        if password is not None:
            print(f"zagv fleet: first-run password: {password}", flush=True)
        return stored

    # ------------------------------------------------------------------ robots' messages

    def _sample_handler(self, topic: str):
        msg_type = codec.topic_type(topic)

        def on_sample(sample: zenoh.Sample) -> None:
            key = str(sample.key_expr)
            try:
                robot_id, _ = split_key(key)
                msg = codec.decode_as(msg_type, sample.payload.to_bytes(), key)
            except (ValueError, codec.ProtoDecodeError) as exc:
                self.node.loop.call_soon_threadsafe(self.node._bad_payload, key, exc)
                return
            self.node.loop.call_soon_threadsafe(self.view.on_message, robot_id, topic, msg)

        return on_sample

    def _on_health(self, sample: zenoh.Sample) -> None:
        try:
            robot_id, name = split_key(str(sample.key_expr))
        except ValueError:
            return
        service = name.rsplit("/", 1)[-1]
        up = sample.kind == zenoh.SampleKind.PUT
        self.node.loop.call_soon_threadsafe(self._health_changed, robot_id, service, up)

    def _health_changed(self, robot_id: str, service: str, up: bool) -> None:
        change = self.view.on_health(robot_id, service, up, time.monotonic())
        if change == "joined":
            log.info("robot %s is at the site", robot_id)
            self._fetch_latched(robot_id)
        elif change == "left":
            log.warning("robot %s left the site (no health token of it reaches the site)", robot_id)

    def _fetch_latched(self, robot_id: str) -> None:
        """Ask a robot that (re)appeared for the last value of each latched topic (map, pose, path, nav status)."""
        for topic in LATCHED:
            handler = self._sample_handler(topic)

            def on_reply(reply: zenoh.Reply, handler=handler) -> None:
                if reply.ok is not None:
                    handler(reply.ok)

            self.node.session.get(f"{ROOT}/{robot_id}/{topic}", zenoh.handlers.Callback(on_reply, lambda: None),
                                  timeout=5.0)

    def close(self) -> None:
        for d in self._declared:
            with contextlib.suppress(Exception):  # already gone with the session
                d.undeclare()

    # ------------------------------------------------------------------ login

    async def login(self, password: str, client: str) -> str | None:
        """A token for the right password, None for a wrong one; LoginThrottled while ``client`` is locked out."""
        return await self.password_login.login(password, client)

    # ------------------------------------------------------------------ commands to one robot

    def _present(self, robot_id: str) -> Keys:
        track = self.view.robots.get(robot_id)
        if track is None:
            raise UnknownRobot(f"no robot {robot_id!r} at this site")
        if not track.present:
            raise RobotUnavailable(f"robot {robot_id} is not reachable from the site (it left)")
        return Keys(robot_id)

    async def _query(self, robot_id: str, name: str, request: Any) -> Any:
        keys = self._present(robot_id)
        try:
            return await query(self.node.session, keys, name, request, timeout_s=self.config.query_timeout_s)
        except QueryError as exc:
            raise RobotUnavailable(f"{robot_id} {name}: {exc}") from None

    async def goal(self, robot_id: str, x: float, y: float, theta: float) -> GoalReply:
        goal_id = f"site-{uuid.uuid4().hex[:8]}"
        reply: GoalReply = await self._query(robot_id, "nav/goal",
                                             GoalRequest(pose=Pose2D(x=x, y=y, theta=theta), id=goal_id))
        if not reply.accepted:
            raise RobotRejected(f"{robot_id} refused the goal: {reply.reason or 'no reason given'}")
        log.info("goal %s (%.2f, %.2f, %.2f) sent to %s", reply.goal_id, x, y, theta, robot_id)
        return reply

    async def poses(self, robot_id: str, poses: list[tuple[float, float, float]]) -> GoalReply:
        request = WaypointsRequest(waypoints=[Waypoint(pose=Pose2D(x=x, y=y, theta=th), id=f"p{i}")
                                              for i, (x, y, th) in enumerate(poses)],
                                   id=f"site-{uuid.uuid4().hex[:8]}")
        reply: GoalReply = await self._query(robot_id, "nav/waypoints", request)
        if not reply.accepted:
            raise RobotRejected(f"{robot_id} refused the pose list: {reply.reason or 'no reason given'}")
        log.info("pose list %s (%d poses) sent to %s", reply.goal_id, len(poses), robot_id)
        return reply

    async def reply_query(self, robot_id: str, name: str, request: Any) -> Reply:
        reply: Reply = await self._query(robot_id, name, request)
        if not reply.ok:
            raise RobotRejected(f"{robot_id} {name} refused: {reply.message or 'no reason given'}")
        return reply

    async def cancel(self, robot_id: str) -> Reply:
        return await self.reply_query(robot_id, "nav/cancel", CancelRequest())

    async def estop(self, robot_id: str) -> Reply:
        return await self.reply_query(robot_id, "drive/estop", Empty())

    # ------------------------------------------------------------------ views

    def snapshot(self) -> dict[str, Any]:
        c = self.config
        return self.view.snapshot(self.robot.chassis_radius_m, (c.battery_empty_v, c.battery_full_v),
                                  c.path_max_points)

    def map_meta(self) -> dict[str, Any]:
        found = self.view.site_map()
        if found is None:
            return {"available": False, "version": 0}
        robot_id, grid = found
        return {"available": True, "version": self.view.map_version, "from": robot_id, "frame": grid.frame,
                "width": grid.width, "height": grid.height, "resolution_m": grid.resolution,
                "origin": {"x": grid.origin.x, "y": grid.origin.y, "theta": grid.origin.theta}}

    def map_png(self) -> bytes | None:
        found = self.view.site_map()
        if found is None:
            return None
        if self._map_png is None or self._map_png[0] != self.view.map_version:
            self._map_png = (self.view.map_version, grid_png(found[1]))
        return self._map_png[1]
