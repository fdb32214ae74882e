"""The simulator service: the clock master, wiring the simulation core to Zenoh, the CAN bus, TCP and a pty.

Timing. The simulator keeps wall pacing itself (it is the clock master; ``--use-sim-time`` does not change its
own timing): physics advances in fixed ``step_s`` steps (5 ms) and sim time is held at ``speed_factor`` x wall
time (``speed_factor <= 0``: free-run, as fast as the machine allows, yielding to the event loop every step).
When it cannot keep up it re-anchors instead of bursting, and the achieved factor is published.

Published: ``clock`` every ``clock_period_s`` of sim time (default 10 ms: services' 20-50 Hz loops wake on
exact multiples without a message per physics step; at 5x that is 500 messages per wall second),
``sim/ground_truth`` at ``ground_truth_hz`` (default 50 Hz sim: the true pose in the world/map frame and the true
body-frame twist; ``collided`` latches on contact until a teleport). Queries: ``sim/teleport`` (moves the robot;
the IMU yaw turns with it) and ``sim/obstacles`` (``add`` with an id and a rect, or the id of a dynamic obstacle
of the world file to activate it; ``remove`` by id; ``clear``).

Hardware: two emulated RoboteQ controllers on the CAN bus (python-can ``remote`` client to the simulated bus;
frames are handled on the event loop as soon as the socket is readable), the emulated LMS111
(``services.sim.lms111``) fed by ``ScanSource``, and a Razor IMU on a pseudo-terminal whose slave is linked at
``imu_link``. All emulated hardware runs on sim time: the sim's own ``SimClock`` is advanced every step and is
the clock the LMS111 emulator and the IMU use.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import select
import time
import tty
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import can

from proto.keys import Keys
from proto.messages import Clock, GroundTruth, ObstacleReply, ObstacleRequest, Pose2D, Reply, TeleportRequest, Twist2D
from services.common.clock import SimClock
from services.common.node import Node, TopicPublisher
from services.common.robot import RobotSpec
from services.common.service import ServiceContext
from services.common.world import World, WorldError, load_world
from services.sim.config import SimConfig
from services.sim.fleet import Fleet, start_poses
from services.sim.lms111 import Lms111Emulator
from services.sim.pacing import Pacer
from services.sim.simulation import Simulation

__all__ = ["SimConfig", "run"]

log = logging.getLogger("zagv.sim")



class CanLink:
    """The controllers' connection to the CAN bus; reconnects when the bus goes away."""

    def __init__(self, sim: Simulation, interface: str, channel: str) -> None:
        self.sim = sim
        self.interface = interface
        self.channel = channel
        self.bus: can.BusABC | None = None
        self.loop = asyncio.get_running_loop()
        self._fd: int | None = None
        self.rx = 0
        self.tx = 0
        self.errors = 0
        self._fast_send: Callable[[list[tuple[int, bytes]]], None] | None = None

    def connect(self) -> bool:
        try:
            self.bus = can.Bus(interface=self.interface, channel=self.channel, receive_own_messages=False)
        except Exception as exc:  # python-can raises many kinds (connection refused, bad channel)
            log.debug("CAN bus %s %s not available: %s", self.interface, self.channel, exc)
            self.bus = None
            return False
        self._fast_send = _remote_fast_sender(self.bus)
        fd = -1
        with contextlib.suppress(Exception):
            fd = self.bus.fileno()
        if isinstance(fd, int) and fd >= 0:
            self._fd = fd
            self.loop.add_reader(fd, self._on_readable)
        log.info("controllers %s on CAN %s %s", ", ".join(str(n.n) for n in self.sim.nodes), self.interface,
                 self.channel)
        return True

    def _on_readable(self) -> None:
        assert self._fd is not None
        for _ in range(256):  # bounded: let the physics loop run between bursts
            if not select.select([self._fd], [], [], 0)[0]:
                return
            if not self.poll_one():
                return

    def poll(self) -> None:
        """For buses without a file descriptor (virtual): drain what is queued."""
        if self.bus is not None and self._fd is None:
            while self.poll_one():
                pass

    def poll_one(self) -> bool:
        try:
            msg = self.bus.recv(0) if self.bus is not None else None
        except Exception as exc:
            self._lost(exc)
            return False
        if msg is None:
            return self._fd is not None  # a non-frame event (remote protocol): keep draining
        if msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame:
            return True
        self.rx += 1
        self.send(self.sim.on_can_frame(msg.arbitration_id, bytes(msg.data)))
        return True

    def send(self, frames: list[tuple[int, bytes]]) -> None:
        if not frames or self.bus is None:
            return
        try:
            if self._fast_send is not None:
                self._fast_send(frames)
            else:
                for can_id, data in frames:
                    self.bus.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=False))
            self.tx += len(frames)
        except Exception as exc:
            self._lost(exc)

    def _lost(self, exc: Exception) -> None:
        self.errors += 1
        log.warning("CAN bus lost (%s); reconnecting", exc)
        self.close()

    def close(self) -> None:
        if self._fd is not None:
            with contextlib.suppress(Exception):
                self.loop.remove_reader(self._fd)
            self._fd = None
        if self.bus is not None:
            with contextlib.suppress(Exception):
                self.bus.shutdown()
            self.bus = None


def _remote_fast_sender(bus: can.BusABC) -> Callable[[list[tuple[int, bytes]]], None] | None:
    """For python-can-remote's binary protocol: write all frames in one ``sendall``.

    The library masks every outgoing WebSocket frame byte by byte in Python (about half of the sim's CAN cost);
    here the frames are built directly, with an all-zero mask (valid WebSocket framing; the bus is loopback only).
    Returns None when the bus is not a python-can-remote client speaking the binary protocol (then ``bus.send``).
    """
    try:
        from can_remote.protocol import BINARY_MESSAGE_TYPE, BINARY_MSG_STRUCT

        protocol = bus.remote_protocol  # type: ignore[attr-defined]
        ws = protocol._ws
        if not protocol._use_binary or not ws.mask:
            return None
        sock, lock = ws.socket, ws._send_lock
    except (AttributeError, ImportError):
        return None
    head = bytes([BINARY_MESSAGE_TYPE])

    def send(frames: list[tuple[int, bytes]]) -> None:
        out = bytearray()
        for can_id, data in frames:
            body = head + BINARY_MSG_STRUCT.pack(0.0, can_id, len(data), 0) + data
            out += bytes((0x82, 0x80 | len(body), 0, 0, 0, 0))  # FIN + binary, masked with a zero key
            out += body
        with lock:
            if ws.closed:
                raise ConnectionError("CAN bus connection closed")
            sock.sendall(out)

    return send


class ImuPty:
    """The Razor IMU's serial port: a pseudo-terminal whose slave path is symlinked at ``link``."""

    def __init__(self, sim: Simulation, link: str) -> None:
        self.sim = sim
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)  # no echo, no CR/LF translation: bytes as a UART would carry them
        os.set_blocking(self.master, False)
        self.slave_path = os.ttyname(self.slave)
        self.link = Path(link)
        self.link.parent.mkdir(parents=True, exist_ok=True)
        with contextlib.suppress(FileNotFoundError):
            self.link.unlink()
        self.link.symlink_to(self.slave_path)
        self.dropped = 0
        asyncio.get_running_loop().add_reader(self.master, self._on_readable)
        log.info("Razor IMU on %s (linked at %s)", self.slave_path, self.link)

    def _on_readable(self) -> None:
        try:
            data = os.read(self.master, 1024)
        except (BlockingIOError, OSError):
            return
        self._write(self.sim.imu.feed(data))

    def tick(self) -> None:
        line = self.sim.imu.due_frame()
        if line:
            self._write(line)

    def _write(self, data: bytes) -> None:
        if not data:
            return
        try:
            os.write(self.master, data)
        except (BlockingIOError, OSError):
            self.dropped += 1  # nobody reads: a UART drops bytes too

    def close(self) -> None:
        with contextlib.suppress(Exception):
            asyncio.get_running_loop().remove_reader(self.master)
        with contextlib.suppress(OSError):
            if self.link.is_symlink():
                self.link.unlink()
        for fd in (self.master, self.slave):
            with contextlib.suppress(OSError):
                os.close(fd)


def teleport_reply(sim: Simulation, req: TeleportRequest, fleet: Fleet | None = None, rid: str = "") -> Reply:
    """``sim/teleport``: move the robot (clears the collision latch); non-finite poses are refused."""
    p = req.pose
    ok = fleet.teleport(rid, p.x, p.y, p.theta) if fleet is not None else sim.teleport(p.x, p.y, p.theta)
    if not ok:
        return Reply(ok=False, message=f"teleport: pose must be finite, got ({p.x}, {p.y}, {p.theta})")
    if fleet is not None and sim.robot.collided:
        note = f" (in contact with {fleet.contact_with[rid]}: the robot cannot move deeper)"
    else:
        note = " (in collision: the robot cannot move deeper)" if sim.robot.collided else ""
    return Reply(ok=True, message=f"robot at ({p.x:.3f}, {p.y:.3f}, {p.theta:.3f}){note}")


def obstacles_reply(world: World, req: ObstacleRequest) -> ObstacleReply:
    """``sim/obstacles``: add (by id, with a rectangle or the world's own), remove one, or clear all."""
    try:
        if req.action == "add":
            if not req.id:
                return ObstacleReply(ok=False, message="add: an id is required", ids=world.active_obstacle_ids())
            world.set_obstacle(req.id, req.rect or None)
            msg = f"obstacle {req.id} active"
        elif req.action == "remove":
            world.remove_obstacle(req.id)
            msg = f"obstacle {req.id} removed"
        else:
            world.clear_obstacles()
            msg = "all dynamic obstacles removed"
    except WorldError as exc:
        return ObstacleReply(ok=False, message=str(exc), ids=world.active_obstacle_ids())
    log.info("%s", msg)
    return ObstacleReply(ok=True, message=msg, ids=world.active_obstacle_ids())


@dataclass
class RobotIo:
    """One simulated robot's I/O: its Zenoh node (keys ``agv/<id>/...``), publishers and devices."""

    rid: str
    sim: Simulation
    node: Node
    clock_pub: TopicPublisher
    truth_pub: TopicPublisher
    link: CanLink
    lidar_port: int
    imu_link: str
    imu: ImuPty | None = None
    lidar: Lms111Emulator | None = None


class SimService:
    """The simulator's devices (CAN nodes, LMS111, Razor IMU) and topics around one Simulation per robot: one
    robot, or a fleet (``[[sim.robots]]``, services.sim.fleet) sharing the world and the clock, each robot under
    its own keys with its own health token."""

    def __init__(self, ctx: ServiceContext, sims: dict[str, Simulation], world: World,
                 fleet: Fleet | None = None) -> None:
        cfg: SimConfig = ctx.config["sim"]
        self.ctx, self.cfg, self.node, self.world, self.fleet = ctx, cfg, ctx.node, world, fleet
        self.sims = sims
        self.first = next(iter(sims.values()))
        self.clock = SimClock()
        self.clock.advance(0.0, cfg.speed_factor)
        self.node.clock = self.clock  # stats report sim time; this service never follows the clock topic
        hardware = {r.id: r for r in cfg.robots}
        self.robots: list[RobotIo] = []
        for rid, sim in sims.items():
            # the service's own node for its own robot id, one more node (same session) per other robot
            node = self.node if rid == ctx.robot.robot_id else Node(self.node.name, self.node.session, Keys(rid))
            node.clock = self.clock  # set after construction: a node built on a SimClock would follow `clock`
            hw = hardware.get(rid)
            # not express: Zenoh batches it, ~2 us per put instead of ~30-40 us, and loopback latency is the same
            io = RobotIo(rid, sim, node, node.publisher("clock"), node.publisher("sim/ground_truth"),
                         CanLink(sim, cfg.can_interface, hw.can_channel if hw else cfg.can_channel),
                         hw.lidar_port if hw else cfg.lidar_port, hw.imu_link if hw else cfg.imu_link)
            node.queryable("sim/teleport", self._teleporter(sim, rid))
            node.queryable("sim/obstacles", lambda req: obstacles_reply(world, req))
            self.robots.append(io)
        self.clock_every = max(1, round(cfg.clock_period_s / cfg.step_s))
        self.truth_every = max(1, round(1.0 / cfg.ground_truth_hz / cfg.step_s))
        self.imu_every = max(1, round(1.0 / cfg.imu_rate_hz / cfg.step_s))
        self.stats: dict[str, float] = {"speed_factor": 0.0, "behind": 0}
        self.node.extra_stats["sim"] = self.stats

    def _teleporter(self, sim: Simulation, rid: str) -> Callable[[TeleportRequest], Reply]:
        return lambda req: teleport_reply(sim, req, self.fleet, rid)

    def contact_of(self, io: RobotIo) -> str:
        if self.fleet is not None:
            return self.fleet.contact_with[io.rid]
        return "wall" if io.sim.robot.collided else ""

    async def start_devices(self) -> None:
        cfg, node = self.cfg, self.node
        for io in self.robots:
            if io.imu_link:
                try:
                    io.imu = ImuPty(io.sim, io.imu_link)
                except OSError as exc:
                    node.log.error("Razor IMU of %s disabled: cannot create %s: %s", io.rid, io.imu_link, exc)
            try:
                # range noise is added once, by the scan source (sim.laser_noise_m); the emulator adds none
                lidar = Lms111Emulator(cfg.lidar_host, io.lidar_port, io.sim.scan_source, self.clock,
                                       frequency_hz=cfg.lidar_frequency_hz, resolution_deg=cfg.lidar_resolution_deg,
                                       range_noise_m=0.0, max_range_m=cfg.laser_max_range_m)
                await lidar.start()
                io.lidar = lidar
            except (OSError, ValueError, TypeError) as exc:
                node.log.error("LMS111 emulator of %s not started on %s:%d: %s", io.rid, cfg.lidar_host,
                               io.lidar_port, exc)

    def ready(self, inputs: str) -> None:
        for io in self.robots:
            io.node.ready(inputs)

    def step(self) -> dict[str, list[tuple[int, bytes]]]:
        if self.fleet is not None:
            return self.fleet.step()
        io = self.robots[0]
        return {io.rid: io.sim.step()}

    def publish_step(self, achieved: float) -> None:
        """After step k: the clock every ``clock_every`` steps (and the world's obstacle schedule), the ground
        truth every ``truth_every``, the IMU every ``imu_every``, for every robot."""
        first = self.first
        k, now_s = first.steps, first.now_s
        self.clock.advance(now_s, achieved)
        if k % self.clock_every == 0:
            tick = Clock(stamp=now_s, speed_factor=achieved)
            for io in self.robots:
                io.clock_pub.put(tick)
            if self.world.dynamic:
                self.world.apply_schedule(now_s)
        if k % self.truth_every == 0:
            for io in self.robots:
                r = io.sim.robot
                io.truth_pub.put(GroundTruth(stamp=now_s, pose=Pose2D(x=r.x, y=r.y, theta=r.theta),
                                             twist=Twist2D(vx=r.vx, vy=r.vy, wz=r.wz, stamp=now_s),
                                             collided=r.collided, contact_with=self.contact_of(io)))
        if k % self.imu_every == 0:
            for io in self.robots:
                if io.imu is not None:
                    io.imu.tick()

    async def run(self) -> None:
        first = self.first
        # wall time below is the sim's own pacing reference (it is the clock master), not robot timing
        pacer = Pacer(self.cfg.speed_factor, time.monotonic(), first.now_s)
        next_connect = 0.0
        while not self.ctx.stop.is_set():
            now_wall = time.monotonic()
            if now_wall >= next_connect:
                for io in self.robots:
                    if io.link.bus is None:
                        if io.link.connect():
                            io.link.send(io.sim.boot())  # power-on (again after a lost bus): boot-up messages
                        else:
                            next_connect = now_wall + 0.5
            wait = pacer.wait_s(now_wall, first.now_s, first.dt, first.steps)
            if wait is not None:
                await asyncio.sleep(wait)
            for io in self.robots:
                io.link.poll()
            frames = self.step()
            for io in self.robots:
                io.link.send(frames[io.rid])
            self.publish_step(pacer.achieved)
            if pacer.measure(now_wall, first.now_s):
                self.stats.update(speed_factor=round(pacer.achieved, 3), behind=pacer.behind,
                                  can_rx=sum(io.link.rx for io in self.robots),
                                  can_tx=sum(io.link.tx for io in self.robots), sim_s=round(first.now_s, 3))

    async def close(self) -> None:
        for io in self.robots:
            if io.lidar is not None:
                with contextlib.suppress(Exception):
                    await io.lidar.stop()
            if io.imu is not None:
                io.imu.close()
            io.link.close()


def build(cfg: SimConfig, robot: RobotSpec, world: World) -> tuple[dict[str, Simulation], Fleet | None]:
    """One Simulation for the robot of ``robot``, or a Fleet for ``[[sim.robots]]`` (starts given or placed)."""
    if not cfg.robots:
        return {robot.robot_id: Simulation(cfg, robot, world)}, None
    cfg.check()
    radius = cfg.footprint_radius_m or robot.chassis_radius_m
    given = [(r.start_pose[0], r.start_pose[1], r.start_pose[2]) for r in cfg.robots if r.start_pose]
    if len(given) not in (0, len(cfg.robots)):
        raise ValueError("[sim] robots: give every robot a start_pose or none")
    starts = start_poses(world, len(cfg.robots), radius, given or [p for _, p in world.robots])
    fleet = Fleet(cfg, robot, world, [r.id for r in cfg.robots], starts)
    return fleet.sims, fleet


async def run(ctx: ServiceContext) -> None:
    cfg: SimConfig = ctx.config["sim"]
    node = ctx.node
    try:
        world = load_world(cfg.world, cfg.map_yaml)
        sims, fleet = build(cfg, ctx.robot, world)
    except (WorldError, ValueError) as exc:
        node.log.error("cannot start: %s", exc)
        raise SystemExit(2) from None
    for rid, sim in sims.items():
        node.log.info("world %s (%dx%d cells at %.3f m), robot %s at (%.2f, %.2f, %.2f)%s", world.name,
                      world.shape[1], world.shape[0], world.resolution_m, rid, sim.robot.x, sim.robot.y,
                      sim.robot.theta, " IN COLLISION" if sim.robot.collided else "")
    service = SimService(ctx, sims, world, fleet)
    await service.start_devices()
    service.ready("world loaded, CAN bus and LMS111 emulation up")
    try:
        await service.run()
    finally:
        await service.close()
