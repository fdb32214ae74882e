"""The drive service's asyncio shell: wires the control loop to Zenoh (cmd_vel in; odom, wheels, imu out; queries).

Topics: subscribes ``cmd_vel`` (on Zenoh's thread, straight into the loop), and ``clock`` in sim mode; publishes
``odom`` and ``wheels`` at ``drive.publish_hz`` (from the loop thread) and ``imu`` when ``drive.imu_port`` is set.
Queries (explicit ``Reply``): ``drive/enable``, ``drive/disable``, ``drive/estop`` (``!EX`` on every controller),
``drive/release`` (``!MG``). A restarted drive (``services.common.lifetime.is_restart``) starts disabled whatever
``drive.auto_enable`` says, and takes over an e-stop the controllers still hold: nothing moves after a restart
without an explicit enable, and an e-stop ends only with an explicit release.
"""

from __future__ import annotations

import asyncio
import logging
import sys
import time

from proto.messages import Empty, Imu, ModuleState, Odometry, Pose2D, Reply, Twist2D, WheelStates
from services.common.lifetime import is_restart
from services.common.service import ServiceContext
from services.drive.canlink import RoboteqLink
from services.drive.config import DriveConfig
from services.drive.controller import DriveController, WheelOdometry
from services.drive.cpu_latency import CpuLatencyError, CpuLatencyRequest
from services.drive.enable import (
    DISABLED,
    ENABLED,
    enable_refusal,
    estop_sent,
    estop_unreachable,
    release_refusal,
    release_sent,
)
from services.drive.imu import ImuSample, RazorReader
from services.drive.kinematics import SwerveKinematics
from services.drive.loop import DriveLoop, LoopSettings, SimTicker, Snapshot, WallTicker

#: the native ring of the drive's cmd_vel and clock subscribers (services.common.node)
CONTROL_QUEUE = 4
log = logging.getLogger("zagv.drive")

#: odometry covariances (x, y, theta), diagonal: wheel odometry is good over short steps, drifts over distance
POSE_COVARIANCE = [1e-3, 0.0, 0.0, 0.0, 1e-3, 0.0, 0.0, 0.0, 2e-3]
TWIST_COVARIANCE = [1e-4, 0.0, 0.0, 0.0, 1e-4, 0.0, 0.0, 0.0, 4e-4]


def build_loop(ctx_robot, cfg: DriveConfig, ticker: WallTicker | SimTicker,
               enabled: bool | None = None) -> DriveLoop:
    """The drive's control loop from the robot spec and the [drive] table (raises ValueError on bad config);
    ``enabled`` (default ``drive.auto_enable``) is its enable state at start."""
    if len(cfg.node_ids) != len(ctx_robot.modules):
        raise ValueError(f"drive.node_ids has {len(cfg.node_ids)} entries but [robot] has "
                         f"{len(ctx_robot.modules)} modules")
    kinematics = SwerveKinematics([(m.x_m, m.y_m) for m in ctx_robot.modules])
    units = cfg.motor_units()
    controller = DriveController(kinematics, units, ctx_robot.twist_limits(), cfg.steering_limits(),
                                 wheel_speed_max_mps=ctx_robot.wheel_speed_max_mps,
                                 hold_speed_mps=cfg.hold_speed_mps, cosine_scaling=cfg.cosine_scaling)
    odometry = WheelOdometry(kinematics, units, max_step_m=cfg.max_odom_step_m)
    settings = LoopSettings(cmd_timeout_s=cfg.cmd_timeout_s, publish_period_s=1.0 / cfg.publish_hz,
                            reconnect_initial_s=cfg.reconnect_initial_s, reconnect_max_s=cfg.reconnect_max_s,
                            fault_mask=cfg.fault_mask, imu_yaw_fusion=cfg.imu_yaw_fusion,
                            imu_yaw_weight=cfg.imu_yaw_weight, imu_timeout_s=cfg.imu_timeout_s,
                            wake_on_command=cfg.wake_on_command, realtime_priority=cfg.realtime_priority,
                            rpdo_refresh_s=cfg.rpdo_refresh_s)
    link_settings = cfg.link_settings()
    return DriveLoop(controller, odometry, lambda: RoboteqLink(link_settings, ticker.now), ticker, settings,
                     enabled=cfg.auto_enable if enabled is None else enabled)


def wheel_states(snap: Snapshot) -> WheelStates:
    modules = []
    for i, cmd in enumerate(snap.result.modules):
        fb = snap.feedback[i] if i < len(snap.feedback) else None
        modules.append(ModuleState(
            steer_rad=snap.measured_angles[i] if fb else 0.0,
            speed_mps=snap.measured_speeds[i] if fb else 0.0,
            steer_cmd_rad=cmd.angle_rad, speed_cmd_mps=cmd.speed_mps,
            traction_amps=fb.traction_amps if fb else 0.0, steer_amps=fb.steer_amps if fb else 0.0,
            traction_counts=fb.traction_counts if fb else 0, steer_counts=fb.steer_counts if fb else 0,
            fault_flags=fb.fault_flags if fb else 0, status_flags=fb.status_flags if fb else 0,
            battery_v=fb.battery_v if fb else 0.0))
    return WheelStates(stamp=snap.stamp, modules=modules, slip_residual_mps=snap.residual_mps,
                       enabled=snap.enabled, estopped=snap.estopped, link_ok=snap.link_ok, fault=snap.fault,
                       loop_hz=snap.loop_hz, loop_jitter_p99_ms=snap.jitter_p99_ms, loop_overruns=snap.overruns)


def odometry_message(snap: Snapshot) -> Odometry:
    x, y, theta = snap.pose
    t = snap.twist
    return Odometry(stamp=snap.stamp, pose=Pose2D(x=x, y=y, theta=theta),
                    twist=Twist2D(vx=t.vx, vy=t.vy, wz=t.wz, stamp=snap.stamp),
                    pose_covariance=list(POSE_COVARIANCE), twist_covariance=list(TWIST_COVARIANCE))


class DriveService:
    """Subscriptions, queries and publishers around the control loop (the loop runs on its own thread)."""

    def __init__(self, ctx: ServiceContext) -> None:
        cfg: DriveConfig = ctx.config["drive"]
        self.ctx, self.cfg, self.node = ctx, cfg, ctx.node
        self.sim = ctx.clock.is_sim
        sim_ticker = SimTicker(cfg.rate_hz) if self.sim else None
        ticker: WallTicker | SimTicker = sim_ticker or WallTicker(cfg.rate_hz, cfg.spin_s)
        if not self.sim:
            # the loop thread must get the GIL back quickly after its sleep: shorten the interpreter's switch interval
            sys.setswitchinterval(min(sys.getswitchinterval(), max(1e-4, 0.25 / cfg.rate_hz)))
        restarted = is_restart("drive")
        self.loop = build_loop(ctx.robot, cfg, ticker, enabled=cfg.auto_enable and not restarted)
        if restarted:
            log.warning("restarted: the drive stays disabled until drive/enable (an e-stop the controllers hold "
                        "stays until drive/release)")
        self.odom_pub = self.node.publisher("odom")
        self.wheels_pub = self.node.publisher("wheels")
        self.stats_due = 0.0
        self.rejected_logged = 0.0
        self.loop.publish = self.publish
        node = self.node
        # nearly latest only (CONTROL_QUEUE): a command or clock tick older than the newest is not worth acting on,
        # and a reader thread that waits for the GIL behind the 1 kHz loop would otherwise work through a backlog of
        # stale ones; a few are kept so that a burst (a bad payload, then a good one) is still seen whole
        if sim_ticker is not None:  # the loop's ticker rides on the node's clock subscription (reader thread)
            node.clock_listeners.append(sim_ticker.advance)
        if cfg.command_source == "safety/cmd_vel":
            node.subscribe("safety/cmd_vel", self.on_cmd, on_zenoh_thread=True, queue=CONTROL_QUEUE)
        else:
            log.warning("taking cmd_vel directly: no collision monitor between the commands and the wheels")
            node.subscribe("cmd_vel", self.on_cmd, on_zenoh_thread=True, queue=CONTROL_QUEUE)
        node.queryable("drive/enable", self.enable)
        node.queryable("drive/disable", self.disable)
        node.queryable("drive/estop", self.estop)
        node.queryable("drive/release", self.release)
        self.imu_reader: RazorReader | None = None
        if cfg.imu_port:
            self.imu_pub = node.publisher("imu")
            self.imu_reader = RazorReader(cfg.imu_port, cfg.imu_baud, self.on_imu)

    def publish(self, snap: Snapshot) -> None:  # loop thread
        self.odom_pub.put(odometry_message(snap))
        self.wheels_pub.put(wheel_states(snap))
        # the @stats figures (percentiles over thousands of samples) are refreshed once per wall second, not at
        # the publish rate: they are read by people and benches
        now = time.monotonic()
        if now < self.stats_due:
            return
        self.stats_due = now + 1.0
        loop = self.loop
        self.node.extra_stats.update(
            link_ok=snap.link_ok, fault=snap.fault, enabled=snap.enabled, estopped=snap.estopped,
            loop_hz=round(snap.loop_hz, 2), loop_jitter_p99_ms=round(snap.jitter_p99_ms, 4),
            loop_overruns=snap.overruns, reconnects=loop.reconnects, cmd_rejected=loop.cmd_rejected,
            refusals=loop.controller.refusals, odom_distance_m=round(loop.odometry.distance_m, 4),
            can_frames_sent=link.frames_sent if (link := loop.link) else 0,
            can_error_frames=link.error_frames if link else 0,
            cmd_to_bus_p50_ms=round(loop.cmd_latency_ms(50), 4), cmd_to_bus_p99_ms=round(loop.cmd_latency_ms(99), 4))

    def on_cmd(self, msg: Twist2D) -> None:  # Zenoh thread
        if not self.loop.set_command(msg.vx, msg.vy, msg.wz):
            now = time.monotonic()
            if now - self.rejected_logged > 1.0:
                self.rejected_logged = now
                log.error("cmd_vel refused: non-finite value in (vx=%r, vy=%r, wz=%r) (%d refused so far)",
                          msg.vx, msg.vy, msg.wz, self.loop.cmd_rejected)

    def on_imu(self, sample: ImuSample) -> None:  # IMU thread
        self.loop.set_imu_yaw_rate(sample.angular_velocity[2])
        self.imu_pub.put(Imu(stamp=self.ctx.clock.now(), yaw=sample.yaw, pitch=sample.pitch, roll=sample.roll,
                             angular_velocity=list(sample.angular_velocity),
                             linear_acceleration=list(sample.linear_acceleration)))

    # ------------------------------------------------------------------ queries (policy: services/drive/enable.py)

    async def enable(self, _: Empty) -> Reply:
        loop = self.loop
        refusal = enable_refusal(loop.estopped, loop.link_ok, loop.link_fault)
        if refusal is not None:
            return refusal
        loop.controller.reset()
        loop.enabled = True
        return ENABLED

    async def disable(self, _: Empty) -> Reply:
        self.loop.enabled = False
        return DISABLED

    async def estop(self, _: Empty) -> Reply:
        loop = self.loop
        loop.estopped = True  # the next cycle commands zero, whatever the controllers answer
        link = loop.link
        unreachable = estop_unreachable(link is not None and loop.link_ok, loop.link_fault)
        if unreachable is not None:
            return unreachable
        assert link is not None  # reachable
        return estop_sent(await asyncio.to_thread(link.estop))

    async def release(self, _: Empty) -> Reply:
        loop = self.loop
        link = loop.link
        refusal = release_refusal(loop.estopped, link is not None and loop.link_ok, loop.link_fault)
        if refusal is not None:
            return refusal
        assert link is not None  # reachable
        reply = release_sent(await asyncio.to_thread(link.release))
        if reply.ok:
            loop.released()
        return reply

    def link_known(self) -> str | None:  # readiness: the CAN link is up, or its first opening failed and says why
        if self.loop.link_ok:
            return "CAN link up"
        return f"CAN link down: {self.loop.link_fault}" if self.loop.link_attempts else None

    def request_cpu_latency(self) -> CpuLatencyRequest | None:
        """Hold ``drive.cpu_latency_us`` while the drive runs; a machine that refuses it costs latency, not the
        drive: a warning names why."""
        if self.cfg.cpu_latency_us is None:
            return None
        try:
            request = CpuLatencyRequest(self.cfg.cpu_latency_us)
        except CpuLatencyError as exc:
            log.warning("drive.cpu_latency_us=%d not applied: %s", self.cfg.cpu_latency_us, exc.strerror)
            return None
        log.info("holding a CPU latency request of %d us while the drive runs", request.latency_us)
        return request

    async def run(self) -> None:
        cpu_latency = self.request_cpu_latency()
        if self.imu_reader is not None:
            self.imu_reader.start()
        self.loop.start()
        self.node.spawn(self.node.ready_when(self.link_known, self.ctx.stop))
        cfg = self.cfg
        log.info("control loop at %.0f Hz on the %s clock, CAN %s %s", cfg.rate_hz, "sim" if self.sim else "wall",
                 cfg.can_interface, cfg.can_channel)
        try:
            await self.ctx.stop.wait()
        finally:
            await asyncio.to_thread(self.loop.stop)
            if self.imu_reader is not None:
                await asyncio.to_thread(self.imu_reader.stop)
            if cpu_latency is not None:
                cpu_latency.close()


async def run(ctx: ServiceContext) -> None:
    logging.getLogger("canopen").setLevel(logging.WARNING)
    logging.getLogger("canopen.sdo.client").setLevel(logging.CRITICAL)  # our LinkError says what failed
    logging.getLogger("can").setLevel(logging.WARNING)
    await DriveService(ctx).run()
