"""The ``[drive]`` table: CAN link, control loop, motor constants, limits, IMU. Defaults fit the simulated robot."""

from __future__ import annotations

import math
from typing import Literal

import msgspec

from services.common.motor_units import MotorUnits
from services.drive.canlink import LinkSettings
from services.drive.cpu_latency import MAX_CPU_LATENCY_US
from services.drive.kinematics import SteeringLimits

_LINK = LinkSettings()  # the link's defaults, repeated nowhere else
#: longest RPDO refresh period accepted: half the RoboteQ's default command watchdog (``RWD`` 1000 ms)
MAX_RPDO_REFRESH_S = 0.5


class DriveConfig(msgspec.Struct, forbid_unknown_fields=True):
    """Drive service settings. Times in s (sim seconds under ``use_sim_time``, except SDO, start-up and reconnect
    times, which are wall seconds like the bus itself); angles in rad; speeds in m/s.
    """

    # CAN link (python-can interface + channel; "remote" + ws://... is the simulated bus); defaults: LinkSettings
    can_interface: str = _LINK.interface
    can_channel: str = _LINK.channel
    can_bitrate: int = _LINK.bitrate
    node_ids: list[int] = msgspec.field(default_factory=lambda: list(_LINK.node_ids))
    heartbeat_period_ms: int = _LINK.heartbeat_period_ms
    heartbeat_timeout_s: float = _LINK.heartbeat_timeout_s
    feedback_timeout_s: float = _LINK.feedback_timeout_s
    sdo_timeout_s: float = _LINK.sdo_timeout_s
    configure_pdos: bool = _LINK.configure_pdos
    tpdo_period_ms: int = _LINK.tpdo_period_ms
    tpdo_slow_period_ms: int = _LINK.tpdo_slow_period_ms
    startup_timeout_s: float = _LINK.startup_timeout_s
    reconnect_initial_s: float = 0.2
    reconnect_max_s: float = 2.0

    # control loop
    rate_hz: float = 100.0
    spin_s: float = 0.0003
    wake_on_command: bool = True
    realtime_priority: int = 0
    #: a PM QoS CPU latency request (us) held while the drive runs (``/dev/cpu_dma_latency``, needs root): 0 keeps
    #: idle CPUs polling, so a command does not wait for a CPU to leave a deep idle state. None = no request. Under
    #: systemd the drive's unit keeps every CPU polling instead (their ``pm_qos_resume_latency_us``; install-units
    #: ``--cpu-poll``, the default)
    cpu_latency_us: int | None = None
    #: RPDO1 goes out when the commands change, and otherwise every ``rpdo_refresh_s`` so that the controllers'
    #: command watchdog (``RWD``, 1000 ms by default) stays fed: CANopen's event-driven PDO with an event timer.
    #: 0 = every cycle. At 100 Hz on the simulated bus, sending unchanged frames every cycle was a third of the
    #: control thread's CPU (two websocket writes per cycle)
    rpdo_refresh_s: float = 0.1
    cmd_timeout_s: float = 0.2
    #: where velocity commands come from: ``safety/cmd_vel`` (the collision monitor's output: nothing reaches the
    #: wheels without passing it) or ``cmd_vel`` (straight from nav and the HMI; for a bench without a laser)
    command_source: Literal["safety/cmd_vel", "cmd_vel"] = "safety/cmd_vel"
    publish_hz: float = 50.0
    auto_enable: bool = True
    fault_mask: int = 0x7F

    # motion
    hold_speed_mps: float = 1e-4
    cosine_scaling: bool = True
    steer_min_rad: float = -2.0 * math.pi
    steer_max_rad: float = 2.0 * math.pi
    max_odom_step_m: float = 0.5

    # motor constants (paper eq. 7, 8), one value for every module unless given per module
    wheel_radius_m: float = 0.1
    gear_ratio: float = 30.0
    traction_counts_per_rev: float = 4096.0
    steer_counts_per_rev: float = 204800.0
    steer_zero_counts: list[int] = msgspec.field(default_factory=lambda: [0, 0])
    traction_sign: list[int] = msgspec.field(default_factory=lambda: [1, 1])
    steer_sign: list[int] = msgspec.field(default_factory=lambda: [1, 1])
    max_rpm: float = 3000.0

    # Razor IMU ("" = off)
    imu_port: str = ""
    imu_baud: int = 57600
    imu_yaw_fusion: bool = False
    imu_yaw_weight: float = 1.0
    imu_timeout_s: float = 0.2

    def __post_init__(self) -> None:
        n = len(self.node_ids)
        for name in ("steer_zero_counts", "traction_sign", "steer_sign"):
            if len(getattr(self, name)) != n:
                raise ValueError(f"drive.{name} needs one value per module ({n}, as node_ids)")
        for name in ("rate_hz", "publish_hz", "cmd_timeout_s", "heartbeat_timeout_s", "feedback_timeout_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"drive.{name} must be a finite number > 0, got {value}")
        if not (math.isfinite(self.rpdo_refresh_s) and 0.0 <= self.rpdo_refresh_s <= MAX_RPDO_REFRESH_S):
            raise ValueError(f"drive.rpdo_refresh_s must be in [0, {MAX_RPDO_REFRESH_S}] s (well under the "
                             f"controllers' command watchdog), got {self.rpdo_refresh_s}")
        if self.cpu_latency_us is not None and not 0 <= self.cpu_latency_us <= MAX_CPU_LATENCY_US:
            raise ValueError(f"drive.cpu_latency_us must be in [0, {MAX_CPU_LATENCY_US}] us or unset, "
                             f"got {self.cpu_latency_us}")
        if not 0.0 <= self.imu_yaw_weight <= 1.0:
            raise ValueError(f"drive.imu_yaw_weight must be in [0, 1], got {self.imu_yaw_weight}")
        if not self.steer_max_rad - self.steer_min_rad >= math.pi:
            raise ValueError("drive.steer_min_rad..steer_max_rad must span at least pi")

    def link_settings(self) -> LinkSettings:
        return LinkSettings(
            interface=self.can_interface, channel=self.can_channel, bitrate=self.can_bitrate,
            node_ids=tuple(self.node_ids), heartbeat_period_ms=self.heartbeat_period_ms,
            heartbeat_timeout_s=self.heartbeat_timeout_s, feedback_timeout_s=self.feedback_timeout_s,
            sdo_timeout_s=self.sdo_timeout_s, configure_pdos=self.configure_pdos,
            tpdo_period_ms=self.tpdo_period_ms,
            tpdo_slow_period_ms=self.tpdo_slow_period_ms, startup_timeout_s=self.startup_timeout_s)

    def motor_units(self) -> list[MotorUnits]:
        return [MotorUnits(wheel_radius_m=self.wheel_radius_m, gear_ratio=self.gear_ratio,
                           traction_counts_per_rev=self.traction_counts_per_rev,
                           steer_counts_per_rev=self.steer_counts_per_rev, steer_zero_counts=self.steer_zero_counts[i],
                           max_rpm=self.max_rpm, traction_sign=self.traction_sign[i], steer_sign=self.steer_sign[i])
                for i in range(len(self.node_ids))]

    def steering_limits(self) -> SteeringLimits:
        return SteeringLimits(self.steer_min_rad, self.steer_max_rad)
