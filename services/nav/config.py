"""The [nav] table: costmaps, planner, controller, goal execution (Nav2 parameter names where the concept matches).

Radii left at 0 take the robot's values ([robot] chassis_radius_m for the footprint and inscribed radius,
inflation_radius_m for the inflation radius: the paper's 0.63 / 0.645 m).
"""

from __future__ import annotations

import math

import msgspec

from services.nav.dwa import DwaConfig


class CostmapConfig(msgspec.Struct, forbid_unknown_fields=True):
    """One costmap ([nav.global_costmap], [nav.local_costmap])."""

    update_frequency_hz: float = 5.0
    publish_frequency_hz: float = 1.0
    inflation_radius_m: float = 0.0
    cost_scaling_factor: float = 10.0
    obstacle_max_range_m: float = 2.5
    raytrace_max_range_m: float = 3.0
    lethal_threshold: int = 65
    track_unknown: bool = True
    size_m: float = 5.0  # local (rolling) window only
    # scan marks this close to a wall of the static map are that wall seen again, not applied (global: 0.15)
    static_wall_tolerance_m: float = 0.0


class NavConfig(msgspec.Struct, forbid_unknown_fields=True):
    """Navigation service configuration ([nav])."""

    controller_frequency_hz: float = 20.0
    planner_frequency_hz: float = 1.0
    status_frequency_hz: float = 5.0
    # scans marked/cleared into the costmaps at most this often (~5 ms each); the local costmap is rebuilt at 5 Hz
    scan_integration_hz: float = 5.0
    footprint: list[list[float]] = msgspec.field(default_factory=list)  # polygon [[x, y], ...]; empty: circle
    footprint_radius_m: float = 0.0
    # added to the footprint (Nav2's footprint_padding): covers the half-cell quantisation of the costmaps
    footprint_padding_m: float = 0.05
    # planner: a step into a cell of cost c is (1 + cost_weight c / 252) times its length (finite, >= 0)
    cost_weight: float = 3.0
    clearance_m: float = 0.3
    allow_unknown: bool = False
    path_spacing_m: float = 0.05
    min_replan_interval_s: float = 0.5  # immediate replans (blocked path) at most this often
    # periodic replans take at most this share of the time (a search of d s is followed by d (1 - duty) / duty)
    planner_max_duty: float = 0.25
    # goal checker (0: the robot's Table 2 tolerances)
    xy_goal_tolerance_m: float = 0.0
    yaw_goal_tolerance_rad: float = 0.0
    # final fine approach (P-controller on the goal pose)
    fine_approach_distance_m: float = 0.35
    fine_xy_target_m: float = 0.004
    fine_yaw_target_rad: float = 0.004
    fine_kp_xy: float = 1.0
    fine_kp_yaw: float = 1.2
    fine_min_speed_mps: float = 0.01
    fine_min_wz_radps: float = 0.02
    fine_timeout_s: float = 20.0
    settle_time_s: float = 0.4
    # once settled, ask localization for an update without motion (odometry drifts since its last update) and
    # correct again if the fresh estimate is off; at most this many times. The goal is judged only once the answer
    # (the updated pose and map->odom) is in hand, or localization said it cannot update, or nothing answered
    # within localization_update_timeout_s of wall time (the query's deadline; localization itself answers
    # within 3 s)
    final_localization_updates: int = 2
    localization_update_timeout_s: float = 10.0
    # the goal checker also requires localization to vouch for the pose (Nav2's checks only the estimate): its
    # position std along the weakest direction times localization_std_factor within xy_goal_tolerance, and its
    # heading std times the factor within yaw_goal_tolerance. Along a direction the scans do not pin (one straight
    # wall in view) the estimate is dead reckoning. A goal not vouched for waits up to localization_vouch_wait_s of
    # sim time for updates at rest (each adds its scan's information: a weakly pinned direction tightens, an
    # unpinned one does not), then fails saying so. 0: no such check
    localization_std_factor: float = 2.0
    localization_vouch_wait_s: float = 10.0
    # turn in place first when the path leaves behind the robot (LMS111 blind sector)
    rotate_first_angle_rad: float = 0.785
    rotate_done_angle_rad: float = 0.15
    rotate_kp: float = 1.5
    # progress checker
    required_movement_radius_m: float = 0.3
    required_movement_angle_rad: float = 0.5
    movement_time_allowance_s: float = 15.0
    # recoveries: escapes per stuck episode (the ladders in navigator.py)
    max_recoveries: int = 6
    recovery_reset_distance_m: float = 2.0  # moved this far from where an episode began: the next one starts afresh
    recovery_wait_s: float = 5.0  # the "wait" escape stands still this long
    controller_patience_s: float = 3.0
    spin_angle_rad: float = 1.57
    backup_distance_m: float = 0.25
    backup_speed_mps: float = 0.08
    recovery_timeout_s: float = 20.0
    # inputs
    pose_timeout_s: float = 2.0
    # a localization correction larger than this clears the obstacle layers (their marks used the wrong pose)
    clear_on_pose_jump_m: float = 0.5
    clear_on_pose_jump_rad: float = 0.35
    #: while localization's verdict is not ``tracking`` the robot holds still (no planning, no driving, no
    #: success); a goal still held after this long fails, naming the verdict
    localization_lost_timeout_s: float = 30.0
    global_costmap: CostmapConfig = msgspec.field(
        default_factory=lambda: CostmapConfig(update_frequency_hz=1.0, static_wall_tolerance_m=0.15))
    local_costmap: CostmapConfig = msgspec.field(default_factory=CostmapConfig)
    dwa: DwaConfig = msgspec.field(default_factory=DwaConfig)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.cost_weight) and self.cost_weight >= 0.0):  # A*'s octile heuristic needs it
            raise ValueError(f"nav.cost_weight must be a finite number >= 0, got {self.cost_weight}")
