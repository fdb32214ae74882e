"""The safety service's asyncio shell: ``cmd_vel``, ``scan``, ``odom`` in; ``safety/cmd_vel``, ``safety/state`` out.

Every command (nav's, the HMI jog's) is filtered by the collision monitor and forwarded at once on
``safety/cmd_vel``, the drive's only command input. A watch every ``watch_period_s`` re-filters the last command
(while younger than ``cmd_timeout_s``) against the newest scan, so an obstacle that appears, or a scan that stops,
changes the command within one watch period even when the commander is silent or slow. ``safety/state`` (latched)
carries the verdict; it is published at once when the action changes and at ``state_publish_hz`` otherwise.
``odom`` poses are noted in the monitor: a late scan is judged where the base is now (moved by the odometry motion
since its stamp), and the pose at a scan's stamp lets the monitor remember what left the scanner's field of view.
Without odometry each scan is judged alone, and only while younger than ``uncorrected_scan_timeout_s``.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
from typing import cast

from proto import array
from proto import messages as m
from services.common.clock import is_fresh
from services.common.service import ServiceContext
from services.safety.config import SafetyConfig
from services.safety.monitor import CollisionMonitor, FieldOfView, Verdict, scan_points


class SafetyNode:
    """Wires a ``CollisionMonitor`` to Zenoh (callbacks on the event loop)."""

    def __init__(self, ctx: ServiceContext, cfg: SafetyConfig) -> None:
        self.ctx = ctx
        self.cfg = cfg
        self.log = ctx.node.log
        self.monitor = CollisionMonitor(cfg.params(ctx.robot.chassis_radius_m))
        self.pub_cmd = ctx.node.publisher("safety/cmd_vel", express=True)
        self.pub_state = ctx.node.publisher("safety/state", latched=True)
        self.last_cmd: m.Twist2D | None = None
        self.last_cmd_at = -math.inf
        self.last_sent: tuple[float, float, float] | None = None
        self.last_action = ""
        self.last_state_at = -math.inf
        self.interventions = 0
        self.stats = ctx.node.extra_stats
        self.stats.update(commands=0, interventions=0, stops=0, bad_scans=0)
        ctx.node.subscribe("scan", self.on_scan)
        ctx.node.subscribe("cmd_vel", self.on_cmd)
        ctx.node.subscribe("odom", self.on_odom)
        self.log.info("collision monitor: footprint radius %.3f m, stop %.2f m, slow-down %.2f m, look-ahead %.1f s",
                      self.monitor.params.robot_radius_m, self.monitor.params.stop_margin_m,
                      self.monitor.params.slowdown_margin_m, self.monitor.params.time_before_collision_s)

    def on_scan(self, msg: m.LaserScan) -> None:
        try:
            ranges = array(msg, "ranges")
        except Exception as exc:  # a malformed byte field: count it, keep the old scan (it ages out)
            self.stats["bad_scans"] += 1
            self.log.warning("dropping a malformed scan: %s", exc)
            return
        values = (msg.stamp, msg.angle_min, msg.angle_increment, msg.range_min, msg.range_max,
                  msg.mount.x, msg.mount.y, msg.mount.theta)
        if not all(math.isfinite(v) for v in values):
            self.stats["bad_scans"] += 1
            return
        points = scan_points(ranges, msg.angle_min, msg.angle_increment, msg.range_min, msg.range_max,
                             (msg.mount.x, msg.mount.y, msg.mount.theta))
        # freshness is judged on this service's clock: a scan counts from when it arrived, never from the future
        now = self.ctx.clock.now()
        stamp = min(msg.stamp, now)
        pose = self.monitor.odom_at(stamp)
        last_beam = msg.angle_min + max(len(ranges) - 1, 0) * msg.angle_increment
        view = FieldOfView((msg.mount.x, msg.mount.y, msg.mount.theta), min(msg.angle_min, last_beam),
                           max(msg.angle_min, last_beam))
        self.monitor.update_scan(points, stamp, pose, view)

    def on_odom(self, msg: m.Odometry) -> None:
        if all(math.isfinite(v) for v in (msg.stamp, msg.pose.x, msg.pose.y, msg.pose.theta)):
            self.monitor.note_odom(msg.stamp, (msg.pose.x, msg.pose.y, msg.pose.theta))

    def on_cmd(self, msg: m.Twist2D) -> None:
        self.stats["commands"] += 1
        self.last_cmd, self.last_cmd_at = msg, self.ctx.clock.now()
        self._forward(msg, self.last_cmd_at)

    def _forward(self, cmd: m.Twist2D, now: float) -> Verdict:
        verdict = self.monitor.filter(cmd.vx, cmd.vy, cmd.wz, now)
        vx, vy, wz = verdict.twist
        self.pub_cmd.put(m.Twist2D(vx=vx, vy=vy, wz=wz, stamp=cmd.stamp))
        self.last_sent = verdict.twist
        if verdict.action != "clear":
            self.interventions += 1
            self.stats["interventions"] = self.interventions
            if verdict.action in ("stop", "no_scan"):
                self.stats["stops"] += 1
        self._state(verdict, cmd, now)
        return verdict

    def _state(self, verdict: Verdict, cmd: m.Twist2D, now: float) -> None:
        changed = verdict.action != self.last_action
        if changed and verdict.action in ("stop", "no_scan"):
            self.log.warning("safety %s: %s", verdict.action, verdict.reason)
        elif changed and self.last_action in ("stop", "no_scan"):
            self.log.info("safety: %s (was %s)", verdict.action, self.last_action)
        if not changed and now - self.last_state_at < 1.0 / self.cfg.state_publish_hz:
            return
        self.last_action, self.last_state_at = verdict.action, now
        vx, vy, wz = verdict.twist
        self.pub_state.put(m.SafetyState(stamp=now, action=cast(m.SafetyAction, verdict.action), scale=verdict.scale,
                                         nearest_m=verdict.nearest_m, reason=verdict.reason, requested=cmd,
                                         commanded=m.Twist2D(vx=vx, vy=vy, wz=wz, stamp=cmd.stamp),
                                         interventions=self.interventions))

    def watch(self) -> None:
        """Re-filter the standing command against the newest scan (and its age)."""
        now = self.ctx.clock.now()
        cmd = self.last_cmd
        if cmd is None or not is_fresh(self.last_cmd_at, now, self.cfg.cmd_timeout_s):
            idle = m.Twist2D()
            verdict = self.monitor.filter(0.0, 0.0, 0.0, now)
            self._state(verdict, idle, now)
            return
        verdict = self.monitor.filter(cmd.vx, cmd.vy, cmd.wz, now)
        if self.last_sent is None or any(abs(a - b) > 1e-9 for a, b in zip(verdict.twist, self.last_sent,
                                                                            strict=True)):
            self._forward(cmd, now)


async def run(ctx: ServiceContext) -> None:
    cfg: SafetyConfig = ctx.config["safety"]
    safety = SafetyNode(ctx, cfg)
    ctx.node.ready("subscriptions and publishers declared")  # it needs no input to filter (no scan: it stops)
    while not ctx.stop.is_set():
        stop = asyncio.ensure_future(ctx.stop.wait())
        sleeper = asyncio.ensure_future(ctx.clock.sleep(cfg.watch_period_s))
        await asyncio.wait({stop, sleeper}, return_when=asyncio.FIRST_COMPLETED)
        for task in (stop, sleeper):
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        safety.watch()
