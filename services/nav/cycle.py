"""One controller cycle of the nav service, as plain code: ``NavCycle.tick(now, planner_idle)`` says what to publish.

Per cycle (``controller_frequency_hz``):

- costmaps: the local one every 1/``local_costmap.update_frequency_hz``, the global one every
  1/``global_costmap.update_frequency_hz`` of clock time, the global one published at its ``publish_frequency_hz``;
- localization trust: while a goal runs and localization's verdict is not ``tracking``, the goal is held (zero
  twist, no replanning) and fails after ``localization_lost_timeout_s``;
- the pose is stale when the older of odometry and localization is more than ``pose_timeout_s`` old: zero twist;
- otherwise the Navigator's twist, a plan request when one is due and the planner is idle, the local plan at 5 Hz,
  a ``localization/nomotion`` request when the Navigator asks for one; one zero twist when the goal ends.

The node publishes what ``tick`` returns and logs its ``log`` lines. ``on_tf``, ``on_pose`` and
``on_localization_answer`` take the inputs that change the cycle's decisions.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import cast

import numpy as np

from proto import messages as m
from services.common.clock import due
from services.nav.config import NavConfig
from services.nav.navigator import TERMINAL, Navigator, PlanRequest
from services.nav.pose_tracker import PoseTracker

LOCAL_PLAN_PERIOD_S = 0.2


@dataclass
class CycleOutput:
    """What one cycle asks the node to do (None / False: nothing)."""

    cmd: tuple[float, float, float] | None = None
    publish_costmap: bool = False
    local_plan: np.ndarray | None = None
    plan_request: PlanRequest | None = None
    request_localization: bool = False
    publish_status_now: bool = False
    log: list[tuple[int, str]] = field(default_factory=list)


class NavCycle:
    """The nav loop's schedule and safety decisions around a Navigator and a PoseTracker (module docstring)."""

    def __init__(self, cfg: NavConfig, nav: Navigator, tracker: PoseTracker, now: float) -> None:
        self.cfg = cfg
        self.nav = nav
        self.tracker = tracker
        self.start(now)
        self.was_active = False
        self.untrusted_since: float | None = None
        self.last_scan_at = -float("inf")
        self._status_signature: tuple[object, ...] = ()

    def start(self, now: float) -> None:
        """Schedule every periodic job from ``now`` (the first cycle runs them all)."""
        self.next_local = self.next_global = self.next_costmap_pub = self.next_status = now
        self.next_local_pub = now

    # ------------------------------------------------------------------ inputs

    def on_scan(self, now: float, msg: m.LaserScan) -> bool:
        """Mark a scan in the costmaps at most ``scan_integration_hz`` times a second; True when it was used."""
        if self.tracker.current() is None or 0.0 <= now - self.last_scan_at < 1.0 / self.cfg.scan_integration_hz:
            return False
        self.last_scan_at = now
        observation = self.tracker.scan_observation(msg)
        if observation is None:
            return False
        self.nav.add_scan(observation)
        return True

    def on_tf(self, msg: m.Transform2D) -> str | None:
        """A map->odom transform; when it moved the pose by more than ``clear_on_pose_jump_m`` / ``_rad`` the marks
        so far were placed with a pose localization now says was wrong (relocalized, kidnapped): the obstacle
        layers are cleared and the returned line says so."""
        jump = self.tracker.on_tf(msg)
        if jump is None:
            return None
        jump_m, jump_rad = jump
        if jump_m > self.cfg.clear_on_pose_jump_m or jump_rad > self.cfg.clear_on_pose_jump_rad:
            self.nav.clear_costmaps()
            return (f"pose jumped {jump_m:.2f} m, {jump_rad:.2f} rad (localization corrected itself): "
                    "obstacle layers cleared")
        return None

    def on_pose(self, now: float, msg: m.PoseWithCovariance) -> None:
        self.tracker.on_pose(msg)

    def on_localization_answer(self, now: float, answer: m.LocalizationUpdate | None) -> str | None:
        """The answer to localization/nomotion (None: none came by the query's deadline). Its pose and map->odom
        are applied before the Navigator hears of it (unless a newer one has arrived already), so the goal is judged
        on the updated estimate whichever way the ``pose`` and ``tf/map_odom`` messages race the answer. Returns a
        line to log when the update made the pose jump."""
        line = None
        if answer is not None and answer.ok and answer.pose is not None and answer.map_odom is not None:
            if answer.map_odom.stamp >= self.tracker.tf_stamp:
                line = self.on_tf(answer.map_odom)
            if answer.pose.stamp >= self.tracker.pose_stamp:
                self.tracker.on_pose(answer.pose)
            self.nav.localization_updated(now)
        else:
            self.nav.localization_unavailable(now)
        return line

    # ------------------------------------------------------------------ the cycle

    def tick(self, now: float, planner_idle: bool) -> CycleOutput:
        out = CycleOutput()
        nav, tracker, cfg = self.nav, self.tracker, self.cfg
        pose = tracker.current()
        if pose is not None and nav.has_map:
            self._update_costmaps(now, pose, out)
        active = nav.goal is not None and nav.state not in TERMINAL and nav.state != "idle"
        untrusted = tracker.loc_state != "tracking"
        if active and untrusted:
            active = self._hold_untrusted(now, out)
        elif not untrusted and self.untrusted_since is not None:
            out.log.append((logging.INFO, "localization tracking again: resuming"))
            self.untrusted_since = None
        if active and pose is not None:
            stale = now - tracker.last_update() > cfg.pose_timeout_s
            if not untrusted and planner_idle and nav.plan_due(now):
                out.plan_request = nav.make_request(pose, now)
            nav.loc_position_std_m, nav.loc_weakest_axis_rad = tracker.position_std_m, tracker.weakest_axis_rad
            nav.loc_heading_std_rad, nav.loc_particle_std_m = tracker.heading_std_rad, tracker.particle_std_m
            if stale or untrusted:
                nav.cmd = (0.0, 0.0, 0.0)
                out.cmd = nav.cmd
            else:
                out.cmd = nav.step(now, pose)
            if nav.localization_request:
                nav.localization_request = False
                out.request_localization = True
            if due(now, self.next_local_pub, LOCAL_PLAN_PERIOD_S):
                out.local_plan = nav.local_plan
                self.next_local_pub = now + LOCAL_PLAN_PERIOD_S
            self.was_active = True
        elif self.was_active:
            out.cmd = (0.0, 0.0, 0.0)
            out.local_plan = np.zeros((0, 3))
            self.was_active = False
        for gid, state, err in nav.take_finished():
            out.log.append((logging.INFO, f"goal {gid} {state}{f': {err}' if err else ''}"))
        status_period_s = 1.0 / cfg.status_frequency_hz
        out.publish_status_now = due(now, self.next_status, status_period_s)
        if out.publish_status_now:
            self.next_status = now + status_period_s
        return out

    def _update_costmaps(self, now: float, pose: tuple[float, float, float], out: CycleOutput) -> None:
        nav, cfg = self.nav, self.cfg
        local_period_s = 1.0 / cfg.local_costmap.update_frequency_hz
        if due(now, self.next_local, local_period_s):
            nav.update_costmaps(pose, "local")
            self.next_local = now + local_period_s
        global_period_s = 1.0 / cfg.global_costmap.update_frequency_hz
        if due(now, self.next_global, global_period_s):
            nav.update_costmaps(pose, "global")
            self.next_global = now + global_period_s
        if cfg.global_costmap.publish_frequency_hz > 0:
            publish_period_s = 1.0 / cfg.global_costmap.publish_frequency_hz
            if due(now, self.next_costmap_pub, publish_period_s):
                out.publish_costmap = True
                self.next_costmap_pub = now + publish_period_s

    def _hold_untrusted(self, now: float, out: CycleOutput) -> bool:
        """Hold the goal while localization does not track; fail it after the timeout. False: no longer active."""
        nav, tracker = self.nav, self.tracker
        if self.untrusted_since is None:
            self.untrusted_since = now
            out.log.append((logging.WARNING, f"localization {tracker.loc_state} ({tracker.loc_detail}): holding "
                                             f"goal {nav.goal.id if nav.goal else ''}"))
        elif now - self.untrusted_since > self.cfg.localization_lost_timeout_s:
            nav.fail(now, f"localization {tracker.loc_state} for {now - self.untrusted_since:.0f} s "
                          f"({tracker.loc_detail})")
            return False
        return True

    # ------------------------------------------------------------------ status

    def status(self, now: float) -> m.NavStatus:
        nav = self.nav
        s = nav.sequence
        goal = m.Pose2D(x=nav.last_goal_pose[0], y=nav.last_goal_pose[1], theta=nav.last_goal_pose[2]) \
            if nav.last_goal_pose else None
        st = m.NavStatus(stamp=now, state=cast(m.NavState, nav.state), goal_id=nav.last_goal_id, goal=goal,
                         distance_left_m=nav.distance_left_m if nav.state not in TERMINAL else 0.0,
                         error=nav.error, recoveries=nav.goal.recoveries if nav.goal else 0)
        if s is not None:
            st.sequence_id = s.id
            st.waypoint_index = s.index if s.index < len(s.waypoints) else -1
            st.waypoint_count = len(s.waypoints)
            st.sequence_paused = s.paused
            st.waypoint_results = [m.WaypointResult(**r) for r in s.results]
        return st

    def status_to_publish(self, now: float, force: bool = False) -> m.NavStatus | None:
        """The status when it changed (state, goal, error, waypoint, pause, results) or ``force``; else None."""
        st = self.status(now)
        signature = (st.state, st.goal_id, st.error, st.waypoint_index, st.sequence_paused, len(st.waypoint_results))
        if force or signature != self._status_signature:
            self._status_signature = signature
            return st
        return None
