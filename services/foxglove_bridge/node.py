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
from typing import Any

import foxglove
from foxglove import channels as fc
from foxglove.websocket import Capability, ChannelView, Client, ClientChannel

from proto import messages as m
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


async def run(ctx: ServiceContext) -> None:
    cfg: FoxgloveConfig = ctx.config["foxglove"]
    node = ctx.node
    robot = ctx.robot
    context = foxglove.Context()
    scan_ch = fc.LaserScanChannel("/scan", context=context)
    map_ch = fc.GridChannel("/map", context=context)
    costmap_ch = fc.GridChannel("/costmap", context=context)
    tf_ch = fc.FrameTransformsChannel("/tf", context=context)
    path_ch = fc.PosesInFrameChannel("/path", context=context)
    local_ch = fc.PosesInFrameChannel("/local_plan", context=context)
    particles_ch = fc.PosesInFrameChannel("/particles", context=context)
    robot_ch = fc.SceneUpdateChannel("/robot", context=context)
    last: dict[str, Any] = {}
    wheels: list[m.WheelStates | None] = [None]
    robot_every_s = 1.0 / cfg.robot_hz if cfg.robot_hz > 0 else math.inf
    last_robot_s = [-math.inf]

    def log(channel: Any, msg: Any, stamp_s: float) -> None:
        channel.log(msg, log_time=convert.timestamp(stamp_s).sec * 1_000_000_000 + convert.timestamp(stamp_s).nsec)

    def resend(topic: str) -> None:
        grid = last.get(topic)
        if grid is not None:
            (map_ch if topic == "/map" else costmap_ch).log(grid)

    async def send_goal(payload: bytes) -> None:
        try:
            x, y, theta = convert.goal_from_json(json.loads(payload))
        except (ValueError, KeyError, TypeError, json.JSONDecodeError) as exc:
            node.log.warning("goal from Foxglove ignored: %s", exc)
            return
        try:
            reply = await node.query("nav/goal", m.GoalRequest(pose=m.Pose2D(x=x, y=y, theta=theta)))
            node.log.info("goal from Foxglove (%.2f, %.2f, %.2f): %s", x, y, theta,
                          "accepted" if reply.accepted else f"rejected: {reply.reason}")
        except Exception as exc:  # noqa: BLE001 - reported, the bridge goes on
            node.log.warning("goal from Foxglove failed: %s", exc)

    listener = Listener(node.loop, resend, lambda p: node.spawn(send_goal(p)))
    listener.goal_topic = cfg.goal_topic
    caps = [Capability.ClientPublish] if cfg.allow_goals else []
    server = foxglove.start_server(name=f"zagv {robot.robot_id}", host=cfg.host, port=cfg.port, capabilities=caps,
                                   server_listener=listener, supported_encodings=["json"] if cfg.allow_goals else None,
                                   context=context)
    node.log.info("Foxglove WebSocket on ws://%s:%d (goals %s)", cfg.host, server.port,
                  "allowed on " + cfg.goal_topic if cfg.allow_goals else "not allowed")
    node.extra_stats.update(port=server.port)

    def on_scan(s: m.LaserScan) -> None:
        log(scan_ch, convert.laser_scan(s), s.stamp)
        log(tf_ch, convert.transforms(s), s.stamp)

    def on_grid(topic: str, channel: Any):
        def handle(g: m.OccupancyGrid) -> None:
            last[topic] = convert.grid(g)
            log(channel, last[topic], g.stamp)
        return handle

    def on_tf(msg: m.Message) -> None:
        stamp = float(getattr(msg, "stamp", 0.0))
        log(tf_ch, convert.transforms(msg), stamp)
        if isinstance(msg, m.Odometry) and stamp - last_robot_s[0] >= robot_every_s:
            last_robot_s[0] = stamp
            log(robot_ch, convert.robot_scene(robot, wheels[0], stamp), stamp)

    def on_wheels(w: m.WheelStates) -> None:
        wheels[0] = w

    def on_poses(channel: Any):
        return lambda p: log(channel, convert.poses(p), p.stamp)

    node.subscribe("scan", on_scan)
    node.subscribe("map", on_grid("/map", map_ch), latched=True)
    node.subscribe("nav/costmap", on_grid("/costmap", costmap_ch))
    node.subscribe("odom", on_tf)
    node.subscribe("tf/map_odom", on_tf, latched=True)
    node.subscribe("wheels", on_wheels)
    node.subscribe("nav/path", on_poses(path_ch))
    node.subscribe("nav/local_plan", on_poses(local_ch))
    node.subscribe("particles", on_poses(particles_ch))
    node.ready(f"Foxglove WebSocket on port {server.port}")
    try:
        await ctx.stop.wait()
    finally:
        server.stop()
