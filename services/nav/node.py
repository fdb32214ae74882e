"""The nav service's asyncio shell: wires the Navigator to Zenoh topics, queries and the clock.

Inputs: ``map`` (latched), ``pose`` (map frame, localization), ``tf/map_odom`` + ``odom`` (the high-rate map pose is
map->odom composed with the odometry pose; without a transform the last ``pose`` is moved on by the odometry since it
arrived), ``scan``. At the goal, once settled, nav asks ``localization/nomotion`` for a fresh estimate and corrects
again when it is off (odometry drifts between filter updates).
Outputs: ``cmd_vel`` at ``controller_frequency_hz`` while a goal runs (then one zero),
``nav/path`` per plan, ``nav/local_plan`` (5 Hz), ``nav/status`` (``status_frequency_hz`` and on every change),
``nav/costmap`` (the global costmap at its publish frequency; costs 0..252 as 0..98, 253 -> 99, 254 -> 100,
255 -> -1 like Nav2's costmap publisher). Queries: ``nav/goal``, ``nav/cancel``, ``nav/waypoints``,
``nav/waypoints/control``, ``nav/clear_costmaps``.
"""

from __future__ import annotations

import asyncio

import numpy as np

from proto import codec
from proto import messages as m
from services.common.clock import Rate
from services.common.grid import YAW_EPS_RAD, axis_aligned
from services.common.query import QueryError
from services.common.service import ServiceContext
from services.nav.config import NavConfig
from services.nav.costmap import INSCRIBED, LETHAL, NO_INFORMATION
from services.nav.cycle import CycleOutput, NavCycle
from services.nav.navigator import Navigator, PlanOutcome, PlanRequest
from services.nav.pose_tracker import Pose, PoseTracker

__all__ = ["NavService", "Pose", "PoseTracker", "costmap_message", "path_message", "run"]


def costmap_message(nav: Navigator, stamp: float) -> m.OccupancyGrid:
    c = nav.global_costmap.master.cost
    out = np.round(c.astype(np.float32) * (98.0 / 252.0)).astype(np.int8)
    out[c == INSCRIBED] = 99
    out[c == LETHAL] = 100
    out[c == NO_INFORMATION] = -1
    mm = nav.global_costmap.master
    return m.OccupancyGrid(stamp=stamp, resolution=mm.resolution, width=mm.width, height=mm.height,
                           origin=m.Pose2D(x=mm.origin_x, y=mm.origin_y), data=out.tobytes())


def path_message(poses: np.ndarray, stamp: float) -> m.Path:
    return m.Path(stamp=stamp, poses=np.asarray(poses, dtype="<f4").reshape(-1, 3).tobytes())


class NavService:
    """Subscriptions, queries and publishers around a NavCycle (all callbacks run on the event loop)."""

    def __init__(self, ctx: ServiceContext) -> None:
        self.ctx = ctx
        self.cfg: NavConfig = ctx.config["nav"]
        self.node, self.clock, self.log = ctx.node, ctx.clock, ctx.node.log
        self.nav = Navigator(self.cfg, ctx.robot)
        self.tracker = PoseTracker()
        self.cycle = NavCycle(self.cfg, self.nav, self.tracker, self.clock.now())
        self.plan_task: asyncio.Task[None] | None = None
        node = self.node
        self.pub_cmd = node.publisher("cmd_vel", express=True)
        self.pub_path = node.publisher("nav/path", latched=True)
        self.pub_local = node.publisher("nav/local_plan")
        self.pub_status = node.publisher("nav/status", latched=True)
        self.pub_costmap = node.publisher("nav/costmap", latched=True, block=False)  # large and periodic: may drop
        node.subscribe("map", self.on_map, latched=True)
        node.subscribe("odom", self.tracker.on_odom)
        node.subscribe("tf/map_odom", self.on_tf, latched=True)  # a restarted nav knows the pose at once
        node.subscribe("pose", lambda msg: self.cycle.on_pose(self.clock.now(), msg), latched=True)
        node.subscribe("scan", lambda msg: self.cycle.on_scan(self.clock.now(), msg))

    # ------------------------------------------------------------------ inputs

    def on_map(self, msg: m.OccupancyGrid) -> None:
        data = codec.array(msg, "data")
        if msg.width <= 0 or msg.height <= 0 or data.size != msg.width * msg.height or not msg.resolution > 0:
            self.log.warning("ignored map: %dx%d cells with %d values, resolution %s", msg.width, msg.height,
                             data.size, msg.resolution)
            return
        grid, ox, oy = axis_aligned(data.reshape(msg.height, msg.width), msg.resolution,
                                    (msg.origin.x, msg.origin.y, msg.origin.theta), fill=-1)
        if abs(msg.origin.theta) > YAW_EPS_RAD:
            self.log.info("map origin has a yaw of %.4f rad: costmaps use it resampled onto %dx%d axis-aligned "
                          "cells", msg.origin.theta, grid.shape[1], grid.shape[0])
        self.nav.set_map(grid, msg.resolution, ox, oy)
        self.log.info("map %dx%d at %.3f m", msg.width, msg.height, msg.resolution)

    def on_tf(self, msg: m.Transform2D) -> None:
        line = self.cycle.on_tf(msg)
        if line is not None:
            self.log.info("%s", line)

    async def request_localization_update(self) -> None:
        """Ask for an update at rest; the cycle gets the answer (or None at the deadline) before the goal is judged."""
        reply: m.LocalizationUpdate | None = None
        try:
            reply = await self.node.query("localization/nomotion", m.Empty(),
                                          timeout_s=self.cfg.localization_update_timeout_s)
        except QueryError as exc:
            self.log.info("no localization update at the goal: %s", exc)
        if reply is not None and not reply.ok:
            self.log.info("localization refused an update at the goal: %s", reply.message)
        line = self.cycle.on_localization_answer(self.clock.now(), reply)
        if line is not None:
            self.log.info("%s", line)

    # ------------------------------------------------------------------ queries

    def publish_status(self, force: bool = False) -> None:
        st = self.cycle.status_to_publish(self.clock.now(), force)
        if st is not None:
            self.pub_status.put(st)

    def current_pose(self) -> tuple[Pose | None, str]:
        pose = self.tracker.current()
        if pose is None:
            return None, "no robot pose yet (is localization running?)"
        return pose, ""

    async def on_goal(self, req: m.GoalRequest) -> m.GoalReply:
        if req.frame != "map":
            return m.GoalReply(accepted=False, goal_id=req.id, reason=f"goal frame {req.frame!r}: only 'map'")
        pose, why = self.current_pose()
        if pose is None:
            return m.GoalReply(accepted=False, goal_id=req.id, reason=why)
        self.nav.sequence = None
        ok, gid, reason = self.nav.start_goal(self.clock.now(), (req.pose.x, req.pose.y, req.pose.theta), req.id)
        if ok:
            self.log.info("goal %s accepted: (%.2f, %.2f, %.2f)", gid, req.pose.x, req.pose.y, req.pose.theta)
        else:
            self.log.warning("goal rejected: %s", reason)
        self.publish_status()
        return m.GoalReply(accepted=ok, goal_id=gid, reason=reason)

    async def on_cancel(self, req: m.CancelRequest) -> m.Reply:
        ok, msg = self.nav.cancel(req.goal_id)
        self.publish_status()
        return m.Reply(ok=ok, message=msg)

    async def on_waypoints(self, req: m.WaypointsRequest) -> m.GoalReply:
        pose, why = self.current_pose()
        if pose is None:
            return m.GoalReply(accepted=False, goal_id=req.id, reason=why)
        wps = [(w.id, (w.pose.x, w.pose.y, w.pose.theta)) for w in req.waypoints]
        ok, sid, reason = self.nav.start_sequence(self.clock.now(), wps, req.id)
        self.publish_status()
        return m.GoalReply(accepted=ok, goal_id=sid, reason=reason)

    async def on_control(self, req: m.WaypointsControl) -> m.Reply:
        ok, msg = self.nav.control_sequence(self.clock.now(), req.action)
        self.publish_status()
        return m.Reply(ok=ok, message=msg)

    async def on_clear(self, _: m.Empty) -> m.Reply:
        self.nav.clear_costmaps()
        pose = self.tracker.current()
        if pose is not None:
            self.nav.update_costmaps(pose)
        return m.Reply(ok=True, message="obstacle layers cleared")

    def declare_queries(self) -> None:
        node = self.node
        node.queryable("nav/goal", self.on_goal)
        node.queryable("nav/cancel", self.on_cancel)
        node.queryable("nav/waypoints", self.on_waypoints)
        node.queryable("nav/waypoints/control", self.on_control)
        node.queryable("nav/clear_costmaps", self.on_clear)

    async def serve_when_ready(self) -> None:
        """Once the map and a pose are in hand (both latched: they come whatever the start order), declare the
        queries and the health token. Until then a goal finds no queryable, and its client waits (query.py)
        instead of being refused for a map nav has not received yet."""
        await self.node.ready_when(
            lambda: "map and pose" if self.nav.has_map and self.tracker.current() is not None else None,
            self.ctx.stop, declare=self.declare_queries)

    # ------------------------------------------------------------------ the loop

    async def plan_job(self, req: PlanRequest) -> None:
        loop = asyncio.get_running_loop()
        t0 = loop.time()
        try:
            out = await loop.run_in_executor(None, self.nav.compute_plan, req)
        except Exception as exc:  # a planner bug must not leave the goal waiting for a plan forever
            self.log.exception("planner failed")
            out = PlanOutcome(np.zeros((0, 3)), f"planner error: {type(exc).__name__}: {exc}", req.goal_seq)
        self.node.extra_stats["last_plan_ms"] = round((loop.time() - t0) * 1000, 1)
        pose = self.tracker.current() or req.start
        self.nav.apply_plan(self.clock.now(), out, pose)
        if out.error:
            self.log.warning("planning failed: %s", out.error)
        elif self.nav.goal is not None and self.nav.goal.seq == out.goal_seq:
            self.pub_path.put(path_message(out.path, self.clock.now()))

    def publish(self, now: float, out: CycleOutput) -> None:
        """Carry out one cycle's output: costmap, plan job, localization request, twist, local plan, logs."""
        if out.publish_costmap:
            self.pub_costmap.put(costmap_message(self.nav, now))
        if out.plan_request is not None:
            self.plan_task = self.node.spawn(self.plan_job(out.plan_request))
        if out.request_localization:
            self.node.spawn(self.request_localization_update())
        if out.cmd is not None:
            vx, vy, wz = out.cmd
            self.pub_cmd.put(m.Twist2D(vx=vx, vy=vy, wz=wz, stamp=now))
        if out.local_plan is not None:
            self.pub_local.put(path_message(out.local_plan, now))
        for level, line in out.log:
            self.log.log(level, "%s", line)

    async def run(self) -> None:
        self.node.spawn(self.serve_when_ready())
        await self.clock.wait_started()
        rate = Rate(self.clock, self.cfg.controller_frequency_hz)
        self.cycle.start(self.clock.now())
        while not self.ctx.stop.is_set():
            now = self.clock.now()
            out = self.cycle.tick(now, planner_idle=self.plan_task is None or self.plan_task.done())
            self.publish(now, out)
            self.publish_status(force=out.publish_status_now)
            if out.publish_status_now:
                self.node.extra_stats["controller"] = {"cycles": rate.cycles, "overruns": rate.overruns}
            await rate.sleep()
        self.pub_cmd.put(m.Twist2D(stamp=self.clock.now()))


async def run(ctx: ServiceContext) -> None:
    await NavService(ctx).run()
