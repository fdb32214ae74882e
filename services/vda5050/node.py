"""The vda5050 service's asyncio shell: MQTT (aiomqtt) on one side, Zenoh on the other, the ``Vehicle`` core between.

MQTT, topics ``{interface}/{major}/{manufacturer}/{serial}/...``: subscribes ``order`` and ``instantActions``;
publishes ``state`` (on every change of the order/action/error/safety picture and at least every
``state_interval_s``), ``visualization`` (``visualization_hz``), ``connection`` (ONLINE retained on connect,
OFFLINE on an orderly stop, CONNECTIONBROKEN as the MQTT last will) and ``factsheet`` (retained, on connect and on
factsheetRequest). The client reconnects after ``reconnect_delay_s`` whenever the broker goes away.

Zenoh inputs: ``map`` (latched), ``pose`` (verdict and match score), ``tf/map_odom`` + ``odom`` (map pose at odometry
rate, as nav computes it), ``wheels`` (e-stop, fault, enable), ``nav/status`` (waypoint results). Queries made:
``nav/waypoints``, ``nav/cancel``, ``localization/initial_pose``.
"""

from __future__ import annotations

import asyncio
import contextlib
import datetime as dt
import json
import math
from typing import Any

import aiomqtt

from proto import codec
from proto import messages as m
from services.common.node import QueryError
from services.common.se2 import compose
from services.common.service import ServiceContext
from services.vda5050.config import Vda5050Config
from services.vda5050.core import (
    DriveTo,
    Effect,
    Headers,
    PublishFactsheet,
    PublishState,
    SetInitialPose,
    StopDriving,
    Vehicle,
    VehicleSettings,
)
from services.vda5050.factsheet import factsheet

Pose = tuple[float, float, float]


def iso_now() -> str:
    """UTC wall time as VDA 5050 writes it (ISO 8601, e.g. 2017-04-15T11:40:03.123Z)."""
    return dt.datetime.now(dt.UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def topic_base(cfg: Vda5050Config, serial: str) -> str:
    return f"{cfg.interface_name}/{cfg.major_version}/{cfg.manufacturer}/{serial}"


class MqttLink:
    """The MQTT session: publishes when connected, drops (and counts) what comes while it is down."""

    def __init__(self, cfg: Vda5050Config, base: str, headers: Headers) -> None:
        self.cfg, self.base, self.headers = cfg, base, headers
        self.client: aiomqtt.Client | None = None
        self.dropped = 0
        self.published: dict[str, int] = {}

    async def publish(self, topic: str, body: dict[str, Any], *, retain: bool = False, qos: int = 0) -> None:
        message = self.headers.wrap(topic, body, iso_now())
        client = self.client
        if client is None:
            self.dropped += 1
            return
        try:
            await client.publish(f"{self.base}/{topic}", json.dumps(message), qos=qos, retain=retain)
            self.published[topic] = self.published.get(topic, 0) + 1
        except aiomqtt.MqttError:
            self.dropped += 1

    def will(self) -> aiomqtt.Will:
        body = self.headers.wrap("connection", {"connectionState": "CONNECTIONBROKEN"}, iso_now())
        return aiomqtt.Will(f"{self.base}/connection", json.dumps(body), qos=1, retain=True)


class Vda5050Service:
    """Zenoh inputs, the Vehicle core's effects and the MQTT session (all on the event loop)."""

    def __init__(self, ctx: ServiceContext) -> None:
        cfg: Vda5050Config = ctx.config["vda5050"]
        robot = ctx.robot
        self.ctx, self.cfg, self.node, self.log = ctx, cfg, ctx.node, ctx.node.log
        serial = cfg.serial_number or robot.robot_id
        self.vehicle = Vehicle(VehicleSettings(
            manufacturer=cfg.manufacturer, serial_number=serial, map_id=cfg.map_id,
            default_deviation_xy_m=cfg.default_deviation_xy_m,
            default_deviation_theta_rad=cfg.default_deviation_theta_rad,
            driving_speed_mps=cfg.driving_speed_mps, driving_turn_radps=cfg.driving_turn_radps,
            battery_empty_v=cfg.battery_empty_v, battery_full_v=cfg.battery_full_v,
            max_message_errors=cfg.max_message_errors, clearance_m=robot.chassis_radius_m))
        self.link = MqttLink(cfg, topic_base(cfg, serial), Headers(cfg.manufacturer, serial, cfg.protocol_version))
        self.sheet = factsheet(robot, cfg)
        self.effects: asyncio.Queue[Effect] = asyncio.Queue()
        self.changed = asyncio.Event()
        self.odom: Pose | None = None
        self.map_odom: Pose | None = None
        self.seen_results: dict[str, int] = {}
        self.last_key = ""
        self.last_state_at = -math.inf
        self.node.extra_stats["mqtt"] = {"broker": f"{cfg.broker_host}:{cfg.broker_port}", "topics": self.link.base}
        node = self.node
        node.subscribe("map", self.on_map, latched=True)
        node.subscribe("odom", self.on_odom)
        node.subscribe("tf/map_odom", self.on_tf, latched=True)
        node.subscribe("pose", self.on_pose, latched=True)
        node.subscribe("wheels", self.on_wheels)
        node.subscribe("nav/status", self.on_nav_status, latched=True)

    def apply(self, out: list[Effect]) -> None:
        for e in out:
            self.effects.put_nowait(e)
        self.changed.set()

    # ------------------------------------------------------------------ Zenoh inputs

    def on_map(self, msg: m.OccupancyGrid) -> None:
        cells = codec.array(msg, "data")
        if msg.width <= 0 or msg.height <= 0 or cells.size != msg.width * msg.height:
            self.log.warning("ignored map of %dx%d cells with %d values", msg.width, msg.height, cells.size)
            return
        vehicle = self.vehicle
        vehicle.set_map(cells.reshape(msg.height, msg.width), msg.resolution, msg.origin.x, msg.origin.y)
        self.log.info("map %dx%d at %.3f m: %d traversable region(s)", msg.width, msg.height, msg.resolution,
                      vehicle.reachability.regions if vehicle.reachability else 0)

    def on_odom(self, msg: m.Odometry) -> None:
        self.odom = odom = (msg.pose.x, msg.pose.y, msg.pose.theta)
        out = self.vehicle.on_velocity(msg.twist.vx, msg.twist.vy, msg.twist.wz)
        if self.map_odom is not None:
            out += self.vehicle.on_pose(*compose(self.map_odom, odom))
        self.apply(out)

    def on_tf(self, msg: m.Transform2D) -> None:
        if all(math.isfinite(v) for v in (msg.x, msg.y, msg.theta)):
            self.map_odom = (msg.x, msg.y, msg.theta)

    def on_pose(self, msg: m.PoseWithCovariance) -> None:
        self.vehicle.on_localization(msg.state, msg.match_score, msg.spread_m)
        out = [] if self.map_odom is not None else self.vehicle.on_pose(msg.pose.x, msg.pose.y, msg.pose.theta)
        self.apply(out)

    def on_wheels(self, msg: m.WheelStates) -> None:
        volts = [mod.battery_v for mod in msg.modules if mod.battery_v > 0 and math.isfinite(mod.battery_v)]
        self.apply(self.vehicle.on_drive(msg.estopped, msg.fault, msg.enabled,
                                         sum(volts) / len(volts) if volts else None))

    def on_nav_status(self, msg: m.NavStatus) -> None:
        vehicle = self.vehicle
        seq = vehicle.driven_sequence
        if not seq or msg.sequence_id != seq:
            return
        out: list[Effect] = []
        for r in msg.waypoint_results[self.seen_results.get(seq, 0):]:
            if r.reached:
                out += vehicle.on_waypoint_reached(r.id)
            elif not r.skipped:
                out += vehicle.on_nav_failed(seq, f"waypoint {r.id}: {r.reason or 'not reached'}")
        self.seen_results[seq] = len(msg.waypoint_results)
        self.apply(out)

    # ------------------------------------------------------------------ effects (in order, one at a time)

    async def drive_to(self, effect: DriveTo) -> None:
        req = m.WaypointsRequest(id=effect.sequence_id, waypoints=[
            m.Waypoint(id=w.id, pose=m.Pose2D(x=w.x, y=w.y, theta=w.theta)) for w in effect.waypoints])
        try:
            reply = await self.node.query("nav/waypoints", req, timeout_s=3.0)
            ok, why = reply.accepted, reply.reason
        except QueryError as exc:
            ok, why = False, str(exc)
        if ok:
            self.log.info("driving %d base node(s) as nav sequence %s", len(effect.waypoints), effect.sequence_id)
        else:
            self.log.warning("nav refused the base: %s", why)
            self.apply(self.vehicle.on_nav_failed(effect.sequence_id, why))

    async def stop_driving(self, effect: StopDriving) -> None:
        try:
            await self.node.query("nav/cancel", m.CancelRequest(), timeout_s=2.0)
        except QueryError as exc:
            self.log.warning("nav/cancel (%s) got no reply: %s", effect.reason, exc)

    async def set_initial_pose(self, effect: SetInitialPose) -> None:
        try:
            reply = await self.node.query("localization/initial_pose", m.InitialPoseRequest(
                pose=m.Pose2D(x=effect.x, y=effect.y, theta=effect.theta)), timeout_s=3.0)
            self.vehicle.action_done(effect.action_id, reply.ok, reply.message)
        except QueryError as exc:
            self.vehicle.action_done(effect.action_id, False, str(exc))

    async def carry_out(self) -> None:
        while True:
            effect = await self.effects.get()
            try:
                if isinstance(effect, DriveTo):
                    await self.drive_to(effect)
                elif isinstance(effect, StopDriving):
                    await self.stop_driving(effect)
                elif isinstance(effect, SetInitialPose):
                    await self.set_initial_pose(effect)
                elif isinstance(effect, PublishFactsheet):
                    await self.link.publish("factsheet", self.sheet, retain=True)
                elif isinstance(effect, PublishState):
                    await self.publish_state()
            except Exception:
                self.log.exception("effect %s failed", effect)
            self.changed.set()

    # ------------------------------------------------------------------ MQTT

    async def publish_state(self) -> None:
        self.last_key = self.vehicle.change_key()
        self.last_state_at = asyncio.get_running_loop().time()
        await self.link.publish("state", self.vehicle.state())

    async def state_reporter(self) -> None:
        loop = asyncio.get_running_loop()
        cfg, link, vehicle = self.cfg, self.link, self.vehicle
        next_vis = loop.time()
        while True:
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self.changed.wait(), 0.1)
            self.changed.clear()
            now = loop.time()
            if link.client is not None:
                if vehicle.change_key() != self.last_key or now - self.last_state_at >= cfg.state_interval_s:
                    await self.publish_state()
                if cfg.visualization_hz > 0 and now >= next_vis:
                    next_vis = now + 1.0 / cfg.visualization_hz
                    await link.publish("visualization", vehicle.visualization())

    async def on_message(self, message: aiomqtt.Message) -> None:
        topic = str(message.topic).rsplit("/", 1)[-1]
        payload = message.payload if isinstance(message.payload, bytes | bytearray) else str(message.payload).encode()
        self.apply(self.vehicle.receive(topic, bytes(payload)))
        self.node.extra_stats["received"] = self.vehicle.received

    async def mqtt_session(self) -> None:
        cfg, link = self.cfg, self.link
        while not self.ctx.stop.is_set():
            try:
                async with aiomqtt.Client(cfg.broker_host, cfg.broker_port, identifier=f"zagv-{link.base}",
                                          username=cfg.broker_username or None,
                                          password=cfg.broker_password or None, will=link.will(),
                                          keepalive=10, clean_session=True) as client:
                    await client.subscribe(f"{link.base}/order", qos=0)
                    await client.subscribe(f"{link.base}/instantActions", qos=0)
                    link.client = client
                    await link.publish("connection", {"connectionState": "ONLINE"}, retain=True, qos=1)
                    await self.publish_state()
                    await link.publish("factsheet", self.sheet, retain=True)
                    self.log.info("connected to MQTT broker %s:%d, topics %s/...", cfg.broker_host, cfg.broker_port,
                                  link.base)
                    async for message in client.messages:
                        await self.on_message(message)
            except aiomqtt.MqttError as exc:
                if link.client is not None:
                    self.log.warning("MQTT connection lost: %s", exc)
                else:
                    self.log.info("MQTT broker %s:%d not reachable: %s", cfg.broker_host, cfg.broker_port, exc)
            finally:
                link.client = None
            await asyncio.sleep(cfg.reconnect_delay_s)

    async def fetch_map(self) -> None:
        """The latched map may have gone out before the subscriber existed: ask for it until it is in hand."""
        while self.vehicle.reachability is None:
            try:
                grid = await self.node.query("map", m.Empty(), timeout_s=2.0)
                if self.vehicle.reachability is None:
                    self.on_map(grid)
            except QueryError as exc:
                self.log.info("no map yet: %s", exc)
            await asyncio.sleep(3.0)

    async def go_offline(self) -> None:
        if self.link.client is not None:
            with contextlib.suppress(aiomqtt.MqttError, asyncio.TimeoutError):
                await asyncio.wait_for(self.link.publish("connection", {"connectionState": "OFFLINE"}, retain=True,
                                                         qos=1), 1.0)


async def run(ctx: ServiceContext) -> None:
    service = Vda5050Service(ctx)
    node = ctx.node
    tasks = [node.spawn(service.carry_out()), node.spawn(service.state_reporter()),
             node.spawn(service.mqtt_session()), node.spawn(service.fetch_map())]
    node.ready("Zenoh subscriptions declared; the MQTT session reports its own link")
    try:
        await ctx.stop.wait()
    finally:
        await service.go_offline()
        for t in tasks:
            t.cancel()
        for t in tasks:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await t
