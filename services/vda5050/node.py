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


async def run(ctx: ServiceContext) -> None:
    cfg: Vda5050Config = ctx.config["vda5050"]
    node, robot = ctx.node, ctx.robot
    log = node.log
    serial = cfg.serial_number or robot.robot_id
    vehicle = Vehicle(VehicleSettings(
        manufacturer=cfg.manufacturer, serial_number=serial, map_id=cfg.map_id,
        default_deviation_xy_m=cfg.default_deviation_xy_m, default_deviation_theta_rad=cfg.default_deviation_theta_rad,
        driving_speed_mps=cfg.driving_speed_mps, driving_turn_radps=cfg.driving_turn_radps,
        battery_empty_v=cfg.battery_empty_v, battery_full_v=cfg.battery_full_v,
        max_message_errors=cfg.max_message_errors, clearance_m=robot.chassis_radius_m))
    headers = Headers(cfg.manufacturer, serial, cfg.protocol_version)
    link = MqttLink(cfg, topic_base(cfg, serial), headers)
    sheet = factsheet(robot, cfg)
    effects: asyncio.Queue[Effect] = asyncio.Queue()
    changed = asyncio.Event()
    node.extra_stats["mqtt"] = {"broker": f"{cfg.broker_host}:{cfg.broker_port}", "topics": link.base}

    def apply(out: list[Effect]) -> None:
        for e in out:
            effects.put_nowait(e)
        changed.set()

    # ------------------------------------------------------------------ Zenoh inputs
    odom: list[Pose | None] = [None]
    map_odom: list[Pose | None] = [None]

    def on_map(msg: m.OccupancyGrid) -> None:
        cells = codec.array(msg, "data")
        if msg.width <= 0 or msg.height <= 0 or cells.size != msg.width * msg.height:
            log.warning("ignored map of %dx%d cells with %d values", msg.width, msg.height, cells.size)
            return
        vehicle.set_map(cells.reshape(msg.height, msg.width), msg.resolution, msg.origin.x, msg.origin.y)
        log.info("map %dx%d at %.3f m: %d traversable region(s)", msg.width, msg.height, msg.resolution,
                 vehicle.reachability.regions if vehicle.reachability else 0)

    def on_odom(msg: m.Odometry) -> None:
        odom[0] = (msg.pose.x, msg.pose.y, msg.pose.theta)
        out = vehicle.on_velocity(msg.twist.vx, msg.twist.vy, msg.twist.wz)
        if map_odom[0] is not None and odom[0] is not None:
            out += vehicle.on_pose(*compose(map_odom[0], odom[0]))
        apply(out)

    def on_tf(msg: m.Transform2D) -> None:
        if all(math.isfinite(v) for v in (msg.x, msg.y, msg.theta)):
            map_odom[0] = (msg.x, msg.y, msg.theta)

    def on_pose(msg: m.PoseWithCovariance) -> None:
        vehicle.on_localization(msg.state, msg.match_score, msg.spread_m)
        out = [] if map_odom[0] is not None else vehicle.on_pose(msg.pose.x, msg.pose.y, msg.pose.theta)
        apply(out)

    def on_wheels(msg: m.WheelStates) -> None:
        volts = [mod.battery_v for mod in msg.modules if mod.battery_v > 0 and math.isfinite(mod.battery_v)]
        apply(vehicle.on_drive(msg.estopped, msg.fault, msg.enabled, sum(volts) / len(volts) if volts else None))

    seen_results: dict[str, int] = {}

    def on_nav_status(msg: m.NavStatus) -> None:
        seq = vehicle.driven_sequence
        if not seq or msg.sequence_id != seq:
            return
        out: list[Effect] = []
        for r in msg.waypoint_results[seen_results.get(seq, 0):]:
            if r.reached:
                out += vehicle.on_waypoint_reached(r.id)
            elif not r.skipped:
                out += vehicle.on_nav_failed(seq, f"waypoint {r.id}: {r.reason or 'not reached'}")
        seen_results[seq] = len(msg.waypoint_results)
        apply(out)

    node.subscribe("map", on_map, latched=True)
    node.subscribe("odom", on_odom)
    node.subscribe("tf/map_odom", on_tf, latched=True)
    node.subscribe("pose", on_pose, latched=True)
    node.subscribe("wheels", on_wheels)
    node.subscribe("nav/status", on_nav_status, latched=True)

    # ------------------------------------------------------------------ effects (in order, one at a time)

    async def carry_out() -> None:
        while True:
            effect = await effects.get()
            try:
                if isinstance(effect, DriveTo):
                    req = m.WaypointsRequest(id=effect.sequence_id, waypoints=[
                        m.Waypoint(id=w.id, pose=m.Pose2D(x=w.x, y=w.y, theta=w.theta)) for w in effect.waypoints])
                    try:
                        reply = await node.query("nav/waypoints", req, timeout_s=3.0)
                        ok, why = reply.accepted, reply.reason
                    except QueryError as exc:
                        ok, why = False, str(exc)
                    if ok:
                        log.info("driving %d base node(s) as nav sequence %s", len(effect.waypoints),
                                 effect.sequence_id)
                    else:
                        log.warning("nav refused the base: %s", why)
                        apply(vehicle.on_nav_failed(effect.sequence_id, why))
                elif isinstance(effect, StopDriving):
                    try:
                        await node.query("nav/cancel", m.CancelRequest(), timeout_s=2.0)
                    except QueryError as exc:
                        log.warning("nav/cancel (%s) got no reply: %s", effect.reason, exc)
                elif isinstance(effect, SetInitialPose):
                    try:
                        reply = await node.query("localization/initial_pose", m.InitialPoseRequest(
                            pose=m.Pose2D(x=effect.x, y=effect.y, theta=effect.theta)), timeout_s=3.0)
                        vehicle.action_done(effect.action_id, reply.ok, reply.message)
                    except QueryError as exc:
                        vehicle.action_done(effect.action_id, False, str(exc))
                elif isinstance(effect, PublishFactsheet):
                    await link.publish("factsheet", sheet, retain=True)
                elif isinstance(effect, PublishState):
                    await publish_state()
            except Exception:
                log.exception("effect %s failed", effect)
            changed.set()

    # ------------------------------------------------------------------ MQTT

    last_key = [""]
    last_state_at = [-math.inf]

    async def publish_state() -> None:
        loop = asyncio.get_running_loop()
        last_key[0] = vehicle.change_key()
        last_state_at[0] = loop.time()
        await link.publish("state", vehicle.state())

    async def state_reporter() -> None:
        loop = asyncio.get_running_loop()
        next_vis = loop.time()
        while True:
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(changed.wait(), 0.1)
            changed.clear()
            now = loop.time()
            if link.client is not None:
                if vehicle.change_key() != last_key[0] or now - last_state_at[0] >= cfg.state_interval_s:
                    await publish_state()
                if cfg.visualization_hz > 0 and now >= next_vis:
                    next_vis = now + 1.0 / cfg.visualization_hz
                    await link.publish("visualization", vehicle.visualization())

    async def on_message(message: aiomqtt.Message) -> None:
        topic = str(message.topic).rsplit("/", 1)[-1]
        payload = message.payload if isinstance(message.payload, bytes | bytearray) else str(message.payload).encode()
        apply(vehicle.receive(topic, bytes(payload)))
        node.extra_stats["received"] = vehicle.received

    async def mqtt_session() -> None:
        while not ctx.stop.is_set():
            try:
                async with aiomqtt.Client(cfg.broker_host, cfg.broker_port, identifier=f"zagv-{link.base}",
                                          username=cfg.broker_username or None,
                                          password=cfg.broker_password or None, will=link.will(),
                                          keepalive=10, clean_session=True) as client:
                    await client.subscribe(f"{link.base}/order", qos=0)
                    await client.subscribe(f"{link.base}/instantActions", qos=0)
                    link.client = client
                    await link.publish("connection", {"connectionState": "ONLINE"}, retain=True, qos=1)
                    await publish_state()
                    await link.publish("factsheet", sheet, retain=True)
                    log.info("connected to MQTT broker %s:%d, topics %s/...", cfg.broker_host, cfg.broker_port,
                             link.base)
                    async for message in client.messages:
                        await on_message(message)
            except aiomqtt.MqttError as exc:
                if link.client is not None:
                    log.warning("MQTT connection lost: %s", exc)
                else:
                    log.info("MQTT broker %s:%d not reachable: %s", cfg.broker_host, cfg.broker_port, exc)
            finally:
                link.client = None
            await asyncio.sleep(cfg.reconnect_delay_s)

    async def fetch_map() -> None:
        """The latched map may have gone out before the subscriber existed: ask for it until it is in hand."""
        while vehicle.reachability is None:
            try:
                grid = await node.query("map", m.Empty(), timeout_s=2.0)
                if vehicle.reachability is None:
                    on_map(grid)
            except QueryError as exc:
                log.info("no map yet: %s", exc)
            await asyncio.sleep(3.0)

    tasks = [node.spawn(carry_out()), node.spawn(state_reporter()), node.spawn(mqtt_session()),
             node.spawn(fetch_map())]
    node.ready("Zenoh subscriptions declared; the MQTT session reports its own link")
    try:
        await ctx.stop.wait()
    finally:
        client = link.client
        if client is not None:
            with contextlib.suppress(aiomqtt.MqttError, asyncio.TimeoutError):
                await asyncio.wait_for(link.publish("connection", {"connectionState": "OFFLINE"}, retain=True,
                                                    qos=1), 1.0)
        for t in tasks:
            t.cancel()
        for t in tasks:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await t
