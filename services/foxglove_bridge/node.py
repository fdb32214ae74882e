"""The Foxglove bridge service: the robot's topics live in Foxglove through the official ``foxglove-sdk``.

Serves the Foxglove WebSocket protocol on ``[foxglove] host:port`` (loopback by default). Channels (Foxglove
schemas, protobuf encoded by the SDK): ``/scan`` (LaserScan), ``/map`` and ``/costmap`` (Grid), ``/tf``
(FrameTransforms: map -> odom -> base_link -> laser), ``/path``, ``/local_plan``, ``/particles`` (PosesInFrame),
``/robot`` (SceneUpdate: footprint and swerve modules). The map and costmap are sent again whenever a client
subscribes, since they change rarely. With ``allow_goals``, a client may publish a pose (JSON
geometry_msgs/PoseStamped or foxglove.PoseInFrame) on ``goal_topic``; it becomes a ``nav/goal`` query.
"""

from __future__ import annotations

import asyncio
import json
import math
from collections.abc import Callable
from typing import Any

import foxglove
from foxglove import channels as fc
from foxglove.websocket import Capability, ChannelView, Client, ClientChannel

from proto import messages as m
from services.common.node import Node
from services.common.robot import RobotSpec
from services.common.service import ServiceContext
from services.foxglove_bridge import convert
from services.foxglove_bridge.config import FoxgloveConfig


class Listener(foxglove.ServerListener):
    """Foxglove server callbacks (on the SDK's threads): re-send grids on subscribe, goals from clients."""

    def __init__(self, loop: asyncio.AbstractEventLoop, on_subscribe, on_goal) -> None:
        self.loop = loop
        self._on_subscribe = on_subscribe
        self._on_goal = on_goal
        self.goal_channels: set[int] = set()
        self.goal_topic = ""

    def on_subscribe(self, client: Client, channel: ChannelView) -> None:
        self.loop.call_soon_threadsafe(self._on_subscribe, channel.topic)

    def on_unsubscribe(self, client: Client, channel: ChannelView) -> None:
        pass

    def on_client_advertise(self, client: Client, channel: ClientChannel) -> None:
        if channel.topic == self.goal_topic and channel.encoding == "json":
            self.goal_channels.add(channel.id)

    def on_client_unadvertise(self, client: Client, client_channel_id: int) -> None:
        self.goal_channels.discard(client_channel_id)

    def on_message_data(self, client: Client, client_channel_id: int, data: bytes) -> None:
        if client_channel_id in self.goal_channels:
            self.loop.call_soon_threadsafe(self._on_goal, bytes(data))


class Channels:
    """The bridge's Foxglove channels and what it keeps between messages: the last grids (re-sent when a client
    subscribes), the last wheel states and when the robot scene was last drawn (odometry stamps, s)."""

    def __init__(self, context: foxglove.Context, robot: RobotSpec, robot_hz: float) -> None:
        self.scan = fc.LaserScanChannel("/scan", context=context)
        self.grids = {"/map": fc.GridChannel("/map", context=context),
                      "/costmap": fc.GridChannel("/costmap", context=context)}
        self.tf = fc.FrameTransformsChannel("/tf", context=context)
        self.path = fc.PosesInFrameChannel("/path", context=context)
        self.local_plan = fc.PosesInFrameChannel("/local_plan", context=context)
        self.particles = fc.PosesInFrameChannel("/particles", context=context)
        self.robot_scene = fc.SceneUpdateChannel("/robot", context=context)
        self.robot = robot
        self.robot_every_s = 1.0 / robot_hz if robot_hz > 0 else math.inf
        self.last_grid: dict[str, Any] = {}
        self.wheels: m.WheelStates | None = None
        self.last_robot_s = -math.inf

    @staticmethod
    def log(channel: Any, msg: Any, stamp_s: float) -> None:
        """Log ``msg`` on ``channel`` with the message's own stamp as the log time (ns)."""
        t = convert.timestamp(stamp_s)
        channel.log(msg, log_time=t.sec * 1_000_000_000 + t.nsec)

    def resend(self, topic: str) -> None:
        """A client subscribed: send it the last grid of ``topic`` (maps change rarely)."""
        grid = self.last_grid.get(topic)
        if grid is not None:
            self.grids[topic].log(grid)

    def on_scan(self, s: m.LaserScan) -> None:
        self.log(self.scan, convert.laser_scan(s), s.stamp)
        self.log(self.tf, convert.transforms(s), s.stamp)

    def on_grid(self, topic: str) -> Callable[[m.OccupancyGrid], None]:
        def handle(g: m.OccupancyGrid) -> None:
            self.last_grid[topic] = convert.grid(g)
            self.log(self.grids[topic], self.last_grid[topic], g.stamp)
        return handle

    def on_tf(self, msg: m.Message) -> None:
        """odom and map->odom as transforms; with odometry, the robot scene at most ``robot_hz``."""
        stamp = float(getattr(msg, "stamp", 0.0))
        self.log(self.tf, convert.transforms(msg), stamp)
        if isinstance(msg, m.Odometry) and stamp - self.last_robot_s >= self.robot_every_s:
            self.last_robot_s = stamp
            self.log(self.robot_scene, convert.robot_scene(self.robot, self.wheels, stamp), stamp)

    def on_wheels(self, w: m.WheelStates) -> None:
        self.wheels = w

    def on_poses(self, channel: Any) -> Callable[[Any], None]:
        return lambda p: self.log(channel, convert.poses(p), p.stamp)


async def send_goal(node: Node, payload: bytes) -> None:
    """A pose a Foxglove client published becomes a ``nav/goal`` query; a bad one is logged and dropped."""
    try:
        x, y, theta = convert.goal_from_json(json.loads(payload))
    except (ValueError, KeyError, TypeError, json.JSONDecodeError) as exc:
        node.log.warning("goal from Foxglove ignored: %s", exc)
        return
    try:
        reply = await node.query("nav/goal", m.GoalRequest(pose=m.Pose2D(x=x, y=y, theta=theta)))
        node.log.info("goal from Foxglove (%.2f, %.2f, %.2f): %s", x, y, theta,
                      "accepted" if reply.accepted else f"rejected: {reply.reason}")
    except Exception as exc:
        node.log.warning("goal from Foxglove failed: %s", exc)


async def run(ctx: ServiceContext) -> None:
    cfg: FoxgloveConfig = ctx.config["foxglove"]
    node = ctx.node
    context = foxglove.Context()
    ch = Channels(context, ctx.robot, cfg.robot_hz)
    listener = Listener(node.loop, ch.resend, lambda p: node.spawn(send_goal(node, p)))
    listener.goal_topic = cfg.goal_topic
    caps = [Capability.ClientPublish] if cfg.allow_goals else []
    server = foxglove.start_server(name=f"zagv {ctx.robot.robot_id}", host=cfg.host, port=cfg.port,
                                   capabilities=caps, server_listener=listener,
                                   supported_encodings=["json"] if cfg.allow_goals else None, context=context)
    node.log.info("Foxglove WebSocket on ws://%s:%d (goals %s)", cfg.host, server.port,
                  "allowed on " + cfg.goal_topic if cfg.allow_goals else "not allowed")
    node.extra_stats.update(port=server.port)
    node.subscribe("scan", ch.on_scan)
    node.subscribe("map", ch.on_grid("/map"), latched=True)
    node.subscribe("nav/costmap", ch.on_grid("/costmap"))
    node.subscribe("odom", ch.on_tf)
    node.subscribe("tf/map_odom", ch.on_tf, latched=True)
    node.subscribe("wheels", ch.on_wheels)
    node.subscribe("nav/path", ch.on_poses(ch.path))
    node.subscribe("nav/local_plan", ch.on_poses(ch.local_plan))
    node.subscribe("particles", ch.on_poses(ch.particles))
    node.ready(f"Foxglove WebSocket on port {server.port}")
    try:
        await ctx.stop.wait()
    finally:
        server.stop()
