"""``[lidar]`` configuration: where the LMS111 is, the scan it should deliver and how the link is supervised."""

from __future__ import annotations

import msgspec

from proto.messages import Pose2D
from services.common.robot import RobotSpec


class LidarConfig(msgspec.Struct, forbid_unknown_fields=True):
    """Defaults fit the simulated robot (the emulated LMS111 on 127.0.0.1:2111)."""

    host: str = "127.0.0.1"
    port: int = 2111
    frequency_hz: float = 25.0  # 25 or 50
    resolution_deg: float = 0.5  # 0.5, or 0.25 at 25 Hz
    range_min_m: float = 0.05
    range_max_m: float = 20.0
    intensities: bool = False
    #: laser pose in base_link; unset: the [robot] laser_mount_* values
    mount_x_m: float | None = None
    mount_y_m: float | None = None
    mount_theta_rad: float | None = None
    #: no scan for this long (s, on the service clock and on wall time) -> reconnect
    watchdog_timeout_s: float = 1.0
    connect_timeout_s: float = 3.0
    reply_timeout_s: float = 3.0
    #: wait at most this long (s) for STlms to report "ready for measurement" (7)
    ready_timeout_s: float = 35.0
    reconnect_min_s: float = 0.2
    #: the backoff's cap: a scanner that comes back (a power cycle, a restarted simulator) streams again within
    #: about this long; a refused connect costs nothing, so retrying each second is cheap
    reconnect_max_s: float = 1.0
    #: SetAccessMode level (3 authorized client, 4 service) and the password's hash ("client" = F4724744)
    login_level: int = 3
    login_password_hash: str = "F4724744"
    #: write mLMPsetscancfg when the scanner's frequency/resolution differ from the ones above
    apply_scan_config: bool = True
    max_telegram_bytes: int = 65536

    def __post_init__(self) -> None:
        if self.frequency_hz not in (25.0, 50.0):
            raise ValueError(f"lidar.frequency_hz must be 25 or 50, got {self.frequency_hz}")
        if self.resolution_deg not in (0.25, 0.5):
            raise ValueError(f"lidar.resolution_deg must be 0.25 or 0.5, got {self.resolution_deg}")
        if self.resolution_deg == 0.25 and self.frequency_hz != 25.0:
            raise ValueError("lidar.resolution_deg 0.25 is only available at lidar.frequency_hz 25 on an LMS111")
        if not 0 <= self.range_min_m < self.range_max_m:
            raise ValueError(f"lidar.range_min_m {self.range_min_m} must be >= 0 and < range_max_m "
                             f"{self.range_max_m}")
        if not 0 < self.port < 65536:
            raise ValueError(f"lidar.port {self.port} is not a TCP port")
        if len(self.login_password_hash) != 8 or any(c not in "0123456789abcdefABCDEF"
                                                     for c in self.login_password_hash):
            raise ValueError(f"lidar.login_password_hash {self.login_password_hash!r} must be 8 hex digits")
        for name in ("watchdog_timeout_s", "connect_timeout_s", "reply_timeout_s", "reconnect_min_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"lidar.{name} must be > 0")
        if self.reconnect_max_s < self.reconnect_min_s:
            raise ValueError("lidar.reconnect_max_s must be >= reconnect_min_s")

    def mount(self, robot: RobotSpec) -> Pose2D:
        """The laser's pose in base_link (config values, else the robot's laser_mount_*)."""
        return Pose2D(
            x=robot.laser_mount_x_m if self.mount_x_m is None else self.mount_x_m,
            y=robot.laser_mount_y_m if self.mount_y_m is None else self.mount_y_m,
            theta=robot.laser_mount_theta_rad if self.mount_theta_rad is None else self.mount_theta_rad,
        )
