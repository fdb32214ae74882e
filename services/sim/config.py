"""The ``[sim]`` table: how the simulated robot, its hardware and its world are set up."""

from __future__ import annotations

import msgspec


class SimRobot(msgspec.Struct, forbid_unknown_fields=True):
    """One robot of a multi-robot world (``[[sim.robots]]``): its id (the ``<id>`` of ``agv/<id>/...``), its start
    ``start_pose`` [x, y, theta] (empty: placed by ``services.sim.fleet.start_poses``), its own CAN bus
    ``can_channel``, its own LMS111 port ``lidar_port`` and its IMU pty ``imu_link`` ("" = no IMU)."""

    id: str
    can_channel: str
    lidar_port: int
    start_pose: list[float] = msgspec.field(default_factory=list)
    imu_link: str = ""


class SimConfig(msgspec.Struct, forbid_unknown_fields=True):
    """Simulator settings (``[sim]``). Times are simulated seconds unless named ``wall``.

    World: ``world`` (built-in name) or ``map_yaml`` (a ROS map YAML; wins when set). ``start_pose`` [x, y, theta]
    (empty: the world's start pose).
    Time: ``speed_factor`` sim s per wall s (<= 0: free-run, as fast as possible); physics every ``step_s``;
    ``clock`` published every ``clock_period_s``; ``sim/ground_truth`` at ``ground_truth_hz``.
    Hardware: RoboteQ nodes ``node_ids`` (module order of ``[robot] modules``) on ``can_interface``/``can_channel``;
    LMS111 emulator on ``lidar_host``:``lidar_port``; Razor IMU pty linked at ``imu_link`` ("" = no IMU).
    Motor units (paper eq. 7, 8): ``wheel_radius_m`` R, ``gear_ratio`` J, ``traction_cpr`` counts per traction
    motor revolution, ``steer_counts_per_rev`` N counts per wheel steering revolution, ``steer_zero_counts`` P0
    per module, ``steer_cpr`` counts per steering motor revolution (relates steering rpm to counts).
    Several robots: ``robots`` (``[[sim.robots]]``, SimRobot) replaces the one robot of ``start_pose``,
    ``can_channel``, ``lidar_port`` and ``imu_link``; every robot shares the world and the clock.
    """

    can_channel: str = "ws://127.0.0.1:54701/"
    can_interface: str = "remote"
    lidar_host: str = "127.0.0.1"
    lidar_port: int = 2111
    speed_factor: float = 1.0
    world: str = "corridor"
    map_yaml: str = ""
    imu_link: str = ""
    start_pose: list[float] = msgspec.field(default_factory=list)
    step_s: float = 0.005
    clock_period_s: float = 0.01
    ground_truth_hz: float = 50.0
    # RoboteQ controllers
    node_ids: list[int] = msgspec.field(default_factory=lambda: [1, 2])
    watchdog_ms: int = 1000
    heartbeat_ms: int = 100
    autostart: bool = False
    tpdo_periods_ms: list[int] = msgspec.field(default_factory=lambda: [20, 20, 100, 100])
    traction_max_rpm: float = 3000.0
    steer_max_rpm: float = 3000.0
    steer_travel_rpm: float = 1500.0
    traction_accel_rpm_s: float = 2000.0
    steer_accel_rpm_s: float = 5000.0
    traction_tau_s: float = 0.02
    steer_limit_counts: float = 0.0
    # motor units
    wheel_radius_m: float = 0.1
    gear_ratio: float = 30.0
    traction_cpr: int = 4096
    steer_counts_per_rev: int = 204800
    steer_cpr: int = 4096
    steer_zero_counts: list[int] = msgspec.field(default_factory=lambda: [0, 0])
    # noise and imperfection (seeded)
    seed: int = 0
    slip_ratio: float = 0.0
    slip_noise: float = 0.0
    encoder_noise_counts: float = 0.0
    laser_max_range_m: float = 20.0
    laser_noise_m: float = 0.012  # the LMS111's statistical error (1 sigma), applied once, by the scan source
    lidar_frequency_hz: float = 25.0  # the scanner's power-up configuration (a client may change it)
    lidar_resolution_deg: float = 0.5
    imu_rate_hz: float = 50.0
    imu_gyro_bias_radps: float = 0.0005
    imu_gyro_noise_radps: float = 0.002
    footprint_radius_m: float = 0.0  # 0: [robot] chassis_radius_m
    robots: list[SimRobot] = msgspec.field(default_factory=list)  # several robots in one world (empty: one robot)

    def check(self) -> None:
        """Raise ValueError naming the first unusable value."""
        def need(ok: bool, what: str) -> None:
            if not ok:
                raise ValueError(f"[sim] {what}")

        need(self.step_s > 0 and self.step_s <= 0.05, f"step_s must be in (0, 0.05] s, got {self.step_s}")
        need(self.clock_period_s >= self.step_s, "clock_period_s must be >= step_s")
        need(self.ground_truth_hz > 0, "ground_truth_hz must be > 0")
        need(len(self.node_ids) == 2 and len(set(self.node_ids)) == 2 and all(1 <= n <= 127 for n in self.node_ids),
             f"node_ids must be two distinct ids in 1..127, got {self.node_ids}")
        need(len(self.steer_zero_counts) == 2, "steer_zero_counts needs one value per module")
        need(self.wheel_radius_m > 0 and self.gear_ratio > 0, "wheel_radius_m and gear_ratio must be > 0")
        need(self.traction_cpr > 0 and self.steer_counts_per_rev > 0 and self.steer_cpr > 0, "counts must be > 0")
        need(len(self.start_pose) in (0, 3), "start_pose must be [] or [x, y, theta]")
        need(len(self.tpdo_periods_ms) <= 4 and all(p >= 0 for p in self.tpdo_periods_ms),
             "tpdo_periods_ms: up to 4 periods >= 0")
        need(self.watchdog_ms >= 0 and self.heartbeat_ms >= 0, "watchdog_ms and heartbeat_ms must be >= 0")
        need(0.0 <= self.slip_ratio < 1.0, "slip_ratio must be in [0, 1)")
        need(self.imu_rate_hz > 0, "imu_rate_hz must be > 0")
        ids = [r.id for r in self.robots]
        need(len(set(ids)) == len(ids), f"robots: ids must be distinct, got {ids}")
        for r in self.robots:
            need(bool(r.id) and not any(c in r.id for c in "/*$?#"),
                 f"robots: id {r.id!r} must be a non-empty key chunk without / * $ ? #")
            need(len(r.start_pose) in (0, 3), f"robots: {r.id}: start_pose must be [] or [x, y, theta]")
        ports = [r.lidar_port for r in self.robots]
        need(len(set(ports)) == len(ports), f"robots: lidar ports must be distinct, got {ports}")
