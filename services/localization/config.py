"""The ``[localization]`` table: map, state folder, mode, initial pose and the AMCL parameters (Nav2 names)."""

from __future__ import annotations

import math
from typing import Literal

from services.localization.amcl import AmclParams


class LocalizationConfig(AmclParams, kw_only=True, forbid_unknown_fields=True):
    """Localization service settings; the AMCL parameters (``max_particles``, ``alpha1`` ...) are inherited.

    - ``map_yaml``: ROS map_server YAML to localize in (and to serve on ``map``).
    - ``state_dir``: folder for the last pose (``localization_pose.json``); empty: nothing is saved.
    - ``mode``: ``navigation`` (AMCL on ``map_yaml``) or ``mapping`` (SLAM).
    - initial pose: ``set_initial_pose`` with ``initial_pose_x/_y`` (m), ``initial_pose_yaw`` (rad) and the
      ``initial_cov_xx/_yy`` (m^2), ``initial_cov_aa`` (rad^2) spread; ``initialize_at_saved_pose`` prefers the pose
      saved by a previous run on the same map (written at ``save_pose_rate`` Hz).
    - ``laser_mount_from_scan``: use the LaserScan's ``mount``; false: the ``[robot]`` laser_mount_* values.
    - odom/scan synchronisation: the odom pose at a scan's stamp is interpolated from ``odom_history_s`` of odom;
      a scan newer than the last odom waits for the odom that passes its stamp (at most ``scan_queue_size`` scans
      wait, as in tf2's MessageFilter: ``scan_queue.py``); past that, the oldest is placed with the last odom pose
      held up to ``scan_odom_tolerance_s``, or dropped.
      Odometry that jumps by more than ``odom_jump_m`` between two messages (drive restarted) re-anchors AMCL.
    - mapping: ``maps_dir`` is where ``localization/save_map`` writes (empty: ``<state_dir>/maps``); a scan is
      processed only after ``mapping_min_travel_m`` / ``mapping_min_turn_rad`` of odometry; the growing map is
      published every ``map_publish_period_s`` (s of clock time). The map frame starts at the initial pose.
      Each scan match is held to the odometry prediction with ``mapping_odom_sigma_xy_m`` /
      ``mapping_odom_sigma_theta_rad`` (1 sigma per processed scan): along a corridor a scan pins the robot only
      to within about a centimetre, and that error would otherwise add up from keyframe to keyframe (the corridor
      came out 1 % long with 0.02 m). Wheel encoders with an IMU are better than that; raise them for a robot
      whose odometry is not. ``mapping_sync`` (slam_toolbox's synchronous mode, for logs played by ``zagv replay``):
      every scan is handled in arrival order, however far behind mapping falls; false (live): when mapping falls
      behind, only the newest scan is kept.
    """

    map_yaml: str = ""
    state_dir: str = ""
    mode: Literal["navigation", "mapping"] = "navigation"
    set_initial_pose: bool = True
    initial_pose_x: float = 0.0
    initial_pose_y: float = 0.0
    initial_pose_yaw: float = 0.0
    initial_cov_xx: float = 0.25
    initial_cov_yy: float = 0.25
    initial_cov_aa: float = (math.pi / 12.0) ** 2
    initialize_at_saved_pose: bool = True
    save_pose_rate: float = 0.5
    laser_mount_from_scan: bool = True
    particles_publish_hz: float = 2.0
    odom_history_s: float = 2.0
    scan_odom_tolerance_s: float = 0.1
    scan_queue_size: int = 10
    odom_jump_m: float = 1.0
    maps_dir: str = ""
    mapping_min_travel_m: float = 0.1
    mapping_min_turn_rad: float = 0.1
    map_publish_period_s: float = 2.0
    mapping_odom_sigma_xy_m: float = 0.003
    mapping_odom_sigma_theta_rad: float = 0.01
    mapping_sync: bool = False

    def __post_init__(self) -> None:
        self.validate()
        for name in ("initial_pose_x", "initial_pose_y", "initial_pose_yaw"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"{name} must be finite")
        for name in ("initial_cov_xx", "initial_cov_yy", "initial_cov_aa"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0")
        for name in ("save_pose_rate", "particles_publish_hz", "scan_odom_tolerance_s"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0")
        if self.scan_queue_size < 0:
            raise ValueError("scan_queue_size must be >= 0")
        if not self.odom_history_s > 0:
            raise ValueError("odom_history_s must be > 0")
        for name in ("mapping_odom_sigma_xy_m", "mapping_odom_sigma_theta_rad"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0")
        for name in ("mapping_min_travel_m", "mapping_min_turn_rad", "map_publish_period_s"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0")
        if not self.odom_jump_m > 0:
            raise ValueError("odom_jump_m must be > 0")

    def amcl_params(self) -> AmclParams:
        """Only the AMCL parameters, as the filter core takes them."""
        fields = {f: getattr(self, f) for f in AmclParams.__struct_fields__}
        return AmclParams(**fields)
