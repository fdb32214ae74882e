"""The simulation core: world + swerve robot + emulated RoboteQ nodes + IMU, advanced in fixed steps.

Pure and synchronous: ``step()`` advances physics by ``step_s`` and returns the CAN frames the controllers send
(heartbeats, TPDOs); ``on_can_frame`` feeds a received frame to the controllers and returns their answers.
The node (``services.sim.node``) does the I/O and the pacing against wall time.
"""

from __future__ import annotations

import math

import numpy as np

from services.common.motor_units import MotorUnits
from services.common.robot import RobotSpec
from services.common.se2 import wrap_angle
from services.common.world import World
from services.sim.config import SimConfig
from services.sim.razor import RazorImu
from services.sim.robot_model import SlipModel, SwerveRobot
from services.sim.roboteq import RoboteqNode, RoboteqSettings
from services.sim.scan_source import ScanSource

Frame = tuple[int, bytes]


class Simulation:
    """One simulated robot in one world. ``now_s`` is sim time (s since start)."""

    def __init__(self, cfg: SimConfig, spec: RobotSpec, world: World) -> None:
        cfg.check()
        if len(spec.modules) != 2:
            raise ValueError(f"the simulator models two swerve modules, [robot] has {len(spec.modules)}")
        self.cfg = cfg
        self.spec = spec
        self.world = world
        self.dt = cfg.step_s
        self.steps = 0
        self.now_s = 0.0
        units = [MotorUnits(wheel_radius_m=cfg.wheel_radius_m, gear_ratio=cfg.gear_ratio,
                            traction_counts_per_rev=cfg.traction_cpr, steer_counts_per_rev=cfg.steer_counts_per_rev,
                            steer_motor_counts_per_rev=cfg.steer_cpr, steer_zero_counts=p0)
                 for p0 in cfg.steer_zero_counts]
        self.robot = SwerveRobot([(m.x_m, m.y_m) for m in spec.modules], units,
                                 SlipModel(cfg.slip_ratio, cfg.slip_noise, cfg.seed))
        for m in self.robot.modules:
            m.traction.tau_s = cfg.traction_tau_s
        self.footprint_radius_m = cfg.footprint_radius_m or spec.chassis_radius_m
        radius = self.footprint_radius_m
        self.robot.margin = lambda x, y: world.clearance_m(x, y, exact_within_m=radius) - radius
        start = cfg.start_pose or list(world.start_pose)
        self.robot.teleport(*map(float, start))
        self.robot.collided = world.circle_collides(self.robot.x, self.robot.y, self.footprint_radius_m)
        noise = None
        if cfg.encoder_noise_counts > 0:
            rng = np.random.default_rng(cfg.seed + 1)
            noise = lambda: cfg.encoder_noise_counts * float(rng.standard_normal())  # noqa: E731
        self.nodes = []
        for node_id, module in zip(cfg.node_ids, self.robot.modules):
            settings = RoboteqSettings(
                node_id=node_id, watchdog_ms=cfg.watchdog_ms, heartbeat_ms=cfg.heartbeat_ms, autostart=cfg.autostart,
                traction_max_rpm=cfg.traction_max_rpm, steer_max_rpm=cfg.steer_max_rpm,
                steer_travel_rpm=cfg.steer_travel_rpm, traction_accel_rpm_s=cfg.traction_accel_rpm_s,
                steer_accel_rpm_s=cfg.steer_accel_rpm_s, tpdo_periods_ms=list(cfg.tpdo_periods_ms),
                steer_limit_counts=cfg.steer_limit_counts)
            self.nodes.append(RoboteqNode(settings, module.traction, module.steer, noise))
        self._node_by_id = {n.n: n for n in self.nodes}
        self.imu = RazorImu(cfg.imu_gyro_bias_radps, cfg.imu_gyro_noise_radps, cfg.seed + 2, self.robot.theta)
        self.scan_source = ScanSource(
            world, self.robot, lambda: self.now_s,
            (spec.laser_mount_x_m, spec.laser_mount_y_m, spec.laser_mount_theta_rad),
            cfg.laser_max_range_m, cfg.laser_noise_m, cfg.seed + 3)  # the only range noise (the emulator adds none)

    # ------------------------------------------------------------------ CAN

    def boot(self) -> list[Frame]:
        """Power on the controllers: their boot-up messages."""
        out: list[Frame] = []
        for n in self.nodes:
            out += n.boot(self.now_s)
        return out

    def on_can_frame(self, can_id: int, data: bytes) -> list[Frame]:
        """A frame seen on the bus; returns the controllers' answers."""
        if 0x580 < can_id < 0x600 or 0x180 < can_id < 0x200 or 0x700 < can_id < 0x780:
            return []  # other nodes' answers, TPDOs and heartbeats
        node = self._node_by_id.get(can_id & 0x7F) if can_id >= 0x600 else None
        if node is not None:
            return node.on_frame(can_id, data, self.now_s)
        out: list[Frame] = []
        for n in self.nodes:
            out += n.on_frame(can_id, data, self.now_s)
        return out

    # ------------------------------------------------------------------ time

    def step(self) -> list[Frame]:
        """Advance one physics step; returns frames the controllers send in it."""
        self.steps += 1
        self.now_s = self.steps * self.dt
        out: list[Frame] = []
        for n in self.nodes:
            out += n.tick(self.now_s)
        self.robot.step(self.dt)
        self.imu.integrate(self.robot.wz, self.dt)
        return out

    def teleport(self, x: float, y: float, theta: float) -> bool:
        """Move the robot; False (and not moved) for non-finite values. Clears the collision latch."""
        if not all(math.isfinite(v) for v in (x, y, theta)):
            return False
        turn = theta - self.robot.theta
        self.robot.teleport(x, y, theta)
        self.imu.yaw_rad = wrap_angle(self.imu.yaw_rad + turn)  # carried: the gyro feels it
        self.robot.collided = self.world.circle_collides(x, y, self.footprint_radius_m)
        return True
