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
import math
import os
import select
import time
import tty
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can

from proto.keys import Keys
from proto.messages import Clock, GroundTruth, ObstacleReply, ObstacleRequest, Pose2D, Reply, TeleportRequest, Twist2D
from services.common.clock import SimClock
from services.common.node import Node
from services.common.service import ServiceContext
from services.sim.config import SimConfig
from services.sim.fleet import Fleet, start_poses
from services.sim.simulation import Simulation
from services.sim.world import WorldError, load_world

try:  # the emulated LMS111 lives in its own module; the sim runs without it
    from services.sim.lms111 import Lms111Emulator
except ImportError:  # pragma: no cover - depends on the checkout
    Lms111Emulator = None

__all__ = ["SimConfig", "run"]

log = logging.getLogger("zagv.sim")

MIN_SLEEP_WALL_S = 0.002


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


@dataclass
class RobotIo:
    """One simulated robot's I/O: its Zenoh node (keys ``agv/<id>/...``), publishers and hardware links."""

    rid: str
    sim: Simulation
    node: Node
    clock_pub: Any = None
    truth_pub: Any = None
    link: CanLink | None = None
    imu: ImuPty | None = None
    lidar: Any = None


async def run(ctx: ServiceContext) -> None:
    cfg: SimConfig = ctx.config["sim"]
    node = ctx.node
    try:
        world = load_world(cfg.world, cfg.map_yaml)
        fleet = None
        if cfg.robots:  # several robots in one world (services.sim.fleet)
            cfg.check()
            radius = cfg.footprint_radius_m or ctx.robot.chassis_radius_m
            given = [tuple(r.start_pose) for r in cfg.robots if r.start_pose]
            if len(given) not in (0, len(cfg.robots)):
                raise ValueError("[sim] robots: give every robot a start_pose or none")
            starts = start_poses(world, len(cfg.robots), radius, given or [p for _, p in world.robots])
            fleet = Fleet(cfg, ctx.robot, world, [r.id for r in cfg.robots], starts)
            sims = fleet.sims
        else:
            sims = {ctx.robot.robot_id: Simulation(cfg, ctx.robot, world)}
    except (WorldError, ValueError) as exc:
        node.log.error("cannot start: %s", exc)
        raise SystemExit(2) from None
    for rid, sim in sims.items():
        node.log.info("world %s (%dx%d cells at %.3f m), robot %s at (%.2f, %.2f, %.2f)%s", world.name,
                      world.shape[1], world.shape[0], world.resolution_m, rid, sim.robot.x, sim.robot.y,
                      sim.robot.theta, " IN COLLISION" if sim.robot.collided else "")
    clock = SimClock()
    clock.advance(0.0, cfg.speed_factor)
    node.clock = clock  # stats report sim time; this service never follows the clock topic
    hardware = {r.id: r for r in cfg.robots}
    robots: list[RobotIo] = []
    for rid, sim in sims.items():
        # every robot's keys: the service's own node for its own id, one more node (same session) per other robot
        rnode = node if rid == ctx.robot.robot_id else Node(node.name, node.session, Keys(rid))
        rnode.clock = clock  # set after construction: a node built on a SimClock would follow the clock topic
        robots.append(RobotIo(rid, sim, rnode))
    sim0_ = next(iter(sims.values()))

    def contact_of(io: RobotIo) -> str:
        if fleet is not None:
            return fleet.contact_with[io.rid]
        return "wall" if io.sim.robot.collided else ""

    def obstacles(req: ObstacleRequest) -> ObstacleReply:
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
        node.log.info("%s", msg)
        return ObstacleReply(ok=True, message=msg, ids=world.active_obstacle_ids())

    for io in robots:
        # not express: Zenoh batches it, ~2 us per put instead of ~30-40 us, and loopback latency is the same
        io.clock_pub = io.node.publisher("clock")
        io.truth_pub = io.node.publisher("sim/ground_truth")

        def teleport(req: TeleportRequest, io: RobotIo = io) -> Reply:
            p = req.pose
            ok = fleet.teleport(io.rid, p.x, p.y, p.theta) if fleet is not None else io.sim.teleport(p.x, p.y, p.theta)
            if not ok:
                return Reply(ok=False, message=f"teleport: pose must be finite, got ({p.x}, {p.y}, {p.theta})")
            note = f" (in contact with {contact_of(io)}: the robot cannot move deeper)" if io.sim.robot.collided else ""
            return Reply(ok=True, message=f"robot at ({p.x:.3f}, {p.y:.3f}, {p.theta:.3f}){note}")

        io.node.queryable("sim/teleport", teleport)
        io.node.queryable("sim/obstacles", obstacles)
        hw = hardware.get(io.rid)
        can_channel = hw.can_channel if hw else cfg.can_channel
        lidar_port = hw.lidar_port if hw else cfg.lidar_port
        imu_link = hw.imu_link if hw else cfg.imu_link
        io.link = CanLink(io.sim, cfg.can_interface, can_channel)
        if imu_link:
            try:
                io.imu = ImuPty(io.sim, imu_link)
            except OSError as exc:
                node.log.error("Razor IMU of %s disabled: cannot create %s: %s", io.rid, imu_link, exc)
        if Lms111Emulator is None:
            node.log.warning("LMS111 emulator unavailable (services.sim.lms111 missing): no laser scanner")
        else:
            try:
                # range noise is added once, by the scan source (sim.laser_noise_m); the emulator adds none
                io.lidar = Lms111Emulator(cfg.lidar_host, lidar_port, io.sim.scan_source, clock,
                                          frequency_hz=cfg.lidar_frequency_hz, resolution_deg=cfg.lidar_resolution_deg,
                                          range_noise_m=0.0, max_range_m=cfg.laser_max_range_m)
                await io.lidar.start()
            except (OSError, ValueError, TypeError) as exc:
                node.log.error("LMS111 emulator of %s not started on %s:%d: %s", io.rid, cfg.lidar_host, lidar_port,
                               exc)
                io.lidar = None

    for io in robots:
        io.node.ready("world loaded, CAN bus and LMS111 emulation up")
    clock_every = max(1, round(cfg.clock_period_s / cfg.step_s))
    truth_every = max(1, round(1.0 / cfg.ground_truth_hz / cfg.step_s))
    imu_every = max(1, round(1.0 / cfg.imu_rate_hz / cfg.step_s))
    free_run = not (cfg.speed_factor > 0 and math.isfinite(cfg.speed_factor))
    stats = {"speed_factor": 0.0, "behind": 0}
    node.extra_stats["sim"] = stats
    # wall time below is the sim's own pacing reference (it is the clock master), not robot timing
    wall0 = time.monotonic()
    sim0 = sim0_.now_s
    meas_wall, meas_sim = wall0, sim0_.now_s
    achieved = cfg.speed_factor if not free_run else 1.0  # replaced by the measured factor after a second
    next_connect = 0.0
    step_all = fleet.step if fleet is not None else (lambda: {robots[0].rid: robots[0].sim.step()})
    try:
        while not ctx.stop.is_set():
            now_wall = time.monotonic()
            if now_wall >= next_connect:
                for io in robots:
                    if io.link.bus is None:
                        if io.link.connect():
                            io.link.send(io.sim.boot())  # power-on (again after a lost bus): boot-up messages
                        else:
                            next_connect = now_wall + 0.5
            now_s = sim0_.now_s
            if free_run:
                await asyncio.sleep(0)
            else:
                due = wall0 + (now_s + sim0_.dt - sim0) / cfg.speed_factor
                delay = due - now_wall
                if delay > 0.0:
                    # wake at most every 2 ms of wall time and catch up in a burst: fewer wake-ups at high factors
                    await asyncio.sleep(max(delay, MIN_SLEEP_WALL_S))
                elif delay < -0.25:  # cannot keep up: re-anchor rather than burst
                    stats["behind"] += 1
                    wall0, sim0 = now_wall, now_s
                elif sim0_.steps % 4 == 0:
                    await asyncio.sleep(0)
            for io in robots:
                io.link.poll()
            frames = step_all()
            for io in robots:
                io.link.send(frames[io.rid])
            k = sim0_.steps
            now_s = sim0_.now_s
            clock.advance(now_s, achieved)
            if k % clock_every == 0:
                tick = Clock(stamp=now_s, speed_factor=achieved)
                for io in robots:
                    io.clock_pub.put(tick)
                if world.dynamic:
                    world.apply_schedule(now_s)
            if k % truth_every == 0:
                for io in robots:
                    r = io.sim.robot
                    io.truth_pub.put(GroundTruth(stamp=now_s, pose=Pose2D(x=r.x, y=r.y, theta=r.theta),
                                                 twist=Twist2D(vx=r.vx, vy=r.vy, wz=r.wz, stamp=now_s),
                                                 collided=r.collided, contact_with=contact_of(io)))
            if k % imu_every == 0:
                for io in robots:
                    if io.imu is not None:
                        io.imu.tick()
            if now_wall - meas_wall >= 1.0:
                achieved = (now_s - meas_sim) / (now_wall - meas_wall)
                stats["speed_factor"] = round(achieved, 3)
                stats.update(can_rx=sum(io.link.rx for io in robots), can_tx=sum(io.link.tx for io in robots),
                             sim_s=round(now_s, 3))
                meas_wall, meas_sim = now_wall, now_s
    finally:
        for io in robots:
            if io.lidar is not None:
                with contextlib.suppress(Exception):
                    await io.lidar.stop()
            if io.imu is not None:
                io.imu.close()
            if io.link is not None:
                io.link.close()
