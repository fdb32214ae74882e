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
import bisect
import math
from collections import deque

import numpy as np

from proto import codec
from proto import messages as m
from services.common.clock import Rate
from services.common.grid import YAW_EPS_RAD, axis_aligned
from services.common.query import QueryError
from services.common.service import ServiceContext
from services.nav.config import NavConfig
from services.nav.costmap import INSCRIBED, LETHAL, NO_INFORMATION, ScanObservation
from services.nav.navigator import TERMINAL, Navigator, PlanOutcome

Pose = tuple[float, float, float]


def compose(a: Pose, b: Pose) -> Pose:
    """a ∘ b on SE(2): pose b given in frame a."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return (a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], a[2] + b[2])


def inverse(a: Pose) -> Pose:
    c, s = math.cos(a[2]), math.sin(a[2])
    return (-c * a[0] - s * a[1], s * a[0] - c * a[1], -a[2])


class PoseTracker:
    """The robot's map pose from localization and odometry (module docstring). Keeps the last ``history_s`` of
    odometry so that a scan is placed with the pose at the time its beams were taken (``at``), not when it
    arrived: a scan processed 50 ms late while turning at 0.5 rad/s would put a wall 2.5 m away 6 cm off."""

    def __init__(self, history_s: float = 2.0) -> None:
        self.history_s = history_s
        self.odom_history: deque[tuple[float, Pose]] = deque()
        self.odom: Pose | None = None
        self.odom_stamp = -math.inf
        self.map_odom: Pose | None = None
        self.pose: Pose | None = None
        self.pose_stamp = -math.inf
        self.tf_stamp = -math.inf
        self.odom_at_pose: Pose | None = None
        #: localization's verdict on its last pose (``tracking`` is the only one nav drives on)
        self.loc_state = "tracking"
        self.loc_detail = ""

    def on_odom(self, msg: m.Odometry) -> None:
        p = (msg.pose.x, msg.pose.y, msg.pose.theta)
        if all(math.isfinite(v) for v in p):
            self.odom, self.odom_stamp = p, msg.stamp
            h = self.odom_history
            if h and msg.stamp < h[-1][0]:
                h.clear()  # time went back (a restarted simulator)
            h.append((msg.stamp, p))
            while h and h[0][0] < msg.stamp - self.history_s:
                h.popleft()

    def odom_at(self, stamp: float) -> Pose | None:
        """Odometry pose at ``stamp``, linearly interpolated (theta along the shorter arc); None outside the
        history."""
        h = self.odom_history
        if not h or not h[0][0] <= stamp <= h[-1][0]:
            return None
        k = bisect.bisect_left(h, stamp, key=lambda e: e[0])
        t1, b = h[k]
        if k == 0 or t1 == stamp:
            return b
        t0, a = h[k - 1]
        f = (stamp - t0) / (t1 - t0) if t1 > t0 else 1.0
        dth = math.remainder(b[2] - a[2], 2 * math.pi)
        return (a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1]), a[2] + f * dth)

    def at(self, stamp: float) -> Pose | None:
        """The map pose at ``stamp`` (map->odom composed with the odometry then); the current pose when the
        odometry history does not cover ``stamp``."""
        odom = self.odom_at(stamp)
        if odom is None or self.map_odom is None:
            return self.current()
        return compose(self.map_odom, odom)

    def on_tf(self, msg: m.Transform2D) -> None:
        p = (msg.x, msg.y, msg.theta)
        if all(math.isfinite(v) for v in p):
            self.map_odom, self.tf_stamp = p, msg.stamp

    def on_pose(self, msg: m.PoseWithCovariance) -> None:
        p = (msg.pose.x, msg.pose.y, msg.pose.theta)
        self.loc_state = msg.state
        self.loc_detail = f"scan match {msg.match_score:.2f}, spread {msg.spread_m:.2f} m"
        if all(math.isfinite(v) for v in p):
            self.pose, self.pose_stamp = p, msg.stamp
            self.odom_at_pose = self.odom

    def current(self) -> Pose | None:
        if self.map_odom is not None and self.odom is not None:
            return compose(self.map_odom, self.odom)
        if self.pose is not None and self.odom is not None and self.odom_at_pose is not None:
            return compose(self.pose, compose(inverse(self.odom_at_pose), self.odom))
        return self.pose

    def last_update(self) -> float:
        """Stamp of the older of the two sources nav drives on: odometry, and localization (``pose`` or
        ``tf/map_odom``, which localization publishes with every scan it uses). A hung drive, lidar or
        localization therefore makes the pose stale and stops the robot (never driving blind on odometry)."""
        return min(self.odom_stamp, max(self.pose_stamp, self.tf_stamp))


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


async def run(ctx: ServiceContext) -> None:
    cfg: NavConfig = ctx.config["nav"]
    node, clock = ctx.node, ctx.clock
    nav = Navigator(cfg, ctx.robot)
    tracker = PoseTracker()
    log = node.log

    pub_cmd = node.publisher("cmd_vel", express=True)
    pub_path = node.publisher("nav/path", latched=True)
    pub_local = node.publisher("nav/local_plan")
    pub_status = node.publisher("nav/status", latched=True)
    pub_costmap = node.publisher("nav/costmap", latched=True, block=False)  # large and periodic: may drop

    def on_map(msg: m.OccupancyGrid) -> None:
        data = codec.array(msg, "data")
        if msg.width <= 0 or msg.height <= 0 or data.size != msg.width * msg.height or not msg.resolution > 0:
            log.warning("ignored map: %dx%d cells with %d values, resolution %s", msg.width, msg.height, data.size,
                        msg.resolution)
            return
        grid, ox, oy = axis_aligned(data.reshape(msg.height, msg.width), msg.resolution,
                                    (msg.origin.x, msg.origin.y, msg.origin.theta), fill=-1)
        if abs(msg.origin.theta) > YAW_EPS_RAD:
            log.info("map origin has a yaw of %.4f rad: costmaps use it resampled onto %dx%d axis-aligned cells",
                     msg.origin.theta, grid.shape[1], grid.shape[0])
        nav.set_map(grid, msg.resolution, ox, oy)
        log.info("map %dx%d at %.3f m", msg.width, msg.height, msg.resolution)

    last_scan = [-math.inf]

    def on_scan(msg: m.LaserScan) -> None:
        now = clock.now()
        if tracker.current() is None or 0.0 <= now - last_scan[0] < 1.0 / cfg.scan_integration_hz:
            return
        last_scan[0] = now
        ranges = codec.array(msg, "ranges")
        if not msg.angle_increment or ranges.size == 0:
            return
        # the sensor pose at the first and the last beam; beams in between are placed on the line between them
        duration = msg.time_increment * (ranges.size - 1) if msg.time_increment > 0 else 0.0
        mount = (msg.mount.x, msg.mount.y, msg.mount.theta)
        first = compose(tracker.at(msg.stamp), mount)
        last = compose(tracker.at(msg.stamp + duration), mount)
        f = np.linspace(0.0, 1.0, ranges.size)
        dth = math.remainder(last[2] - first[2], 2 * math.pi)
        xs = first[0] + f * (last[0] - first[0])
        ys = first[1] + f * (last[1] - first[1])
        angles = first[2] + f * dth + msg.angle_min + np.arange(ranges.size) * msg.angle_increment
        nav.add_scan(ScanObservation(xs, ys, angles, ranges, msg.range_min, msg.range_max))

    node.subscribe("map", on_map, latched=True)
    node.subscribe("odom", tracker.on_odom)
    def on_tf(msg: m.Transform2D) -> None:
        before = tracker.current()
        tracker.on_tf(msg)
        after = tracker.current()
        if before is None or after is None:
            return
        jump_m = math.hypot(after[0] - before[0], after[1] - before[1])
        jump_rad = abs(math.remainder(after[2] - before[2], 2 * math.pi))
        if jump_m > cfg.clear_on_pose_jump_m or jump_rad > cfg.clear_on_pose_jump_rad:
            # the marks so far were placed with a pose localization now says was wrong (relocalized, kidnapped)
            nav.clear_costmaps()
            log.info("pose jumped %.2f m, %.2f rad (localization corrected itself): obstacle layers cleared",
                     jump_m, jump_rad)

    node.subscribe("tf/map_odom", on_tf, latched=True)  # a restarted nav knows the pose at once
    loc_state = {"answered": False}

    def on_pose(msg: m.PoseWithCovariance) -> None:
        tracker.on_pose(msg)
        if loc_state["answered"]:  # the first estimate after a requested no-motion update
            loc_state["answered"] = False
            nav.localization_updated(clock.now())

    async def request_localization_update() -> None:
        # armed before asking: the updated pose can arrive before the reply does
        loc_state["answered"] = True
        try:
            reply = await node.query("localization/nomotion", m.Empty(), timeout_s=1.0)
        except QueryError as exc:
            loc_state["answered"] = False
            log.info("no localization update at the goal: %s", exc)
            return
        if not reply.ok:
            loc_state["answered"] = False
            log.info("localization refused an update at the goal: %s", reply.message)

    node.subscribe("pose", on_pose, latched=True)
    node.subscribe("scan", on_scan)

    def status() -> m.NavStatus:
        s = nav.sequence
        goal = m.Pose2D(x=nav.last_goal_pose[0], y=nav.last_goal_pose[1], theta=nav.last_goal_pose[2]) \
            if nav.last_goal_pose else None
        st = m.NavStatus(stamp=clock.now(), state=nav.state, goal_id=nav.last_goal_id, goal=goal,
                         distance_left_m=nav.distance_left_m if nav.state not in TERMINAL else 0.0,
                         error=nav.error, recoveries=nav.goal.recoveries if nav.goal else 0)
        if s is not None:
            st.sequence_id = s.id
            st.waypoint_index = s.index if s.index < len(s.waypoints) else -1
            st.waypoint_count = len(s.waypoints)
            st.sequence_paused = s.paused
            st.waypoint_results = [m.WaypointResult(**r) for r in s.results]
        return st

    last_status: list[tuple] = [()]

    def publish_status(force: bool = False) -> None:
        st = status()
        sig = (st.state, st.goal_id, st.error, st.waypoint_index, st.sequence_paused, len(st.waypoint_results))
        if force or sig != last_status[0]:
            pub_status.put(st)
            last_status[0] = sig

    def current_pose() -> tuple[Pose | None, str]:
        pose = tracker.current()
        if pose is None:
            return None, "no robot pose yet (is localization running?)"
        return pose, ""

    async def on_goal(req: m.GoalRequest) -> m.GoalReply:
        if req.frame != "map":
            return m.GoalReply(accepted=False, goal_id=req.id, reason=f"goal frame {req.frame!r}: only 'map'")
        pose, why = current_pose()
        if pose is None:
            return m.GoalReply(accepted=False, goal_id=req.id, reason=why)
        nav.sequence = None
        ok, gid, reason = nav.start_goal(clock.now(), (req.pose.x, req.pose.y, req.pose.theta), req.id)
        if ok:
            log.info("goal %s accepted: (%.2f, %.2f, %.2f)", gid, req.pose.x, req.pose.y, req.pose.theta)
        else:
            log.warning("goal rejected: %s", reason)
        publish_status()
        return m.GoalReply(accepted=ok, goal_id=gid, reason=reason)

    async def on_cancel(req: m.CancelRequest) -> m.Reply:
        ok, msg = nav.cancel(req.goal_id)
        publish_status()
        return m.Reply(ok=ok, message=msg)

    async def on_waypoints(req: m.WaypointsRequest) -> m.GoalReply:
        pose, why = current_pose()
        if pose is None:
            return m.GoalReply(accepted=False, goal_id=req.id, reason=why)
        wps = [(w.id, (w.pose.x, w.pose.y, w.pose.theta)) for w in req.waypoints]
        ok, sid, reason = nav.start_sequence(clock.now(), wps, req.id)
        publish_status()
        return m.GoalReply(accepted=ok, goal_id=sid, reason=reason)

    async def on_control(req: m.WaypointsControl) -> m.Reply:
        ok, msg = nav.control_sequence(clock.now(), req.action)
        publish_status()
        return m.Reply(ok=ok, message=msg)

    async def on_clear(_: m.Empty) -> m.Reply:
        nav.clear_costmaps()
        pose = tracker.current()
        if pose is not None:
            nav.update_costmaps(pose)
        return m.Reply(ok=True, message="obstacle layers cleared")

    async def serve_when_ready() -> None:
        """Once the map and a pose are in hand (both latched: they come whatever the start order), declare the
        queries and the health token. Until then a goal finds no queryable, and its client waits (query.py)
        instead of being refused for a map nav has not received yet."""
        await node.ready_when(lambda: "map and pose" if nav.has_map and tracker.current() is not None else None,
                              ctx.stop, declare=lambda: [node.queryable("nav/goal", on_goal),
                                                         node.queryable("nav/cancel", on_cancel),
                                                         node.queryable("nav/waypoints", on_waypoints),
                                                         node.queryable("nav/waypoints/control", on_control),
                                                         node.queryable("nav/clear_costmaps", on_clear)])

    node.spawn(serve_when_ready())

    if getattr(clock, "is_sim", False):
        await clock.wait_started()  # type: ignore[attr-defined]
    loop = asyncio.get_running_loop()
    rate = Rate(clock, cfg.controller_frequency_hz)
    next_local = next_global = next_costmap_pub = next_status = next_local_pub = clock.now()
    was_active = False
    untrusted_since: float | None = None
    plan_task: asyncio.Task | None = None

    async def plan_job(req) -> None:  # noqa: ANN001
        t0 = loop.time()
        try:
            out = await loop.run_in_executor(None, nav.compute_plan, req)
        except Exception as exc:  # a planner bug must not leave the goal waiting for a plan forever
            log.exception("planner failed")
            out = PlanOutcome(np.zeros((0, 3)), f"planner error: {type(exc).__name__}: {exc}", req.goal_seq)
        node.extra_stats["last_plan_ms"] = round((loop.time() - t0) * 1000, 1)
        pose = tracker.current() or req.start
        nav.apply_plan(clock.now(), out, pose)
        if out.error:
            log.warning("planning failed: %s", out.error)
        elif nav.goal is not None and nav.goal.seq == out.goal_seq:
            pub_path.put(path_message(out.path, clock.now()))

    while not ctx.stop.is_set():
        now = clock.now()
        pose = tracker.current()
        if pose is not None and nav.has_map:
            if now >= next_local:
                nav.update_costmaps(pose, "local")
                next_local = now + 1.0 / cfg.local_costmap.update_frequency_hz
            if now >= next_global:
                nav.update_costmaps(pose, "global")
                next_global = now + 1.0 / cfg.global_costmap.update_frequency_hz
            if now >= next_costmap_pub and cfg.global_costmap.publish_frequency_hz > 0:
                pub_costmap.put(costmap_message(nav, now))
                next_costmap_pub = now + 1.0 / cfg.global_costmap.publish_frequency_hz
        active = nav.goal is not None and nav.state not in TERMINAL and nav.state != "idle"
        untrusted = tracker.loc_state != "tracking"
        if active and untrusted:
            if untrusted_since is None:
                untrusted_since = now
                log.warning("localization %s (%s): holding goal %s", tracker.loc_state, tracker.loc_detail,
                            nav.goal.id if nav.goal else "")
            elif now - untrusted_since > cfg.localization_lost_timeout_s:
                nav.fail(now, f"localization {tracker.loc_state} for {now - untrusted_since:.0f} s "
                              f"({tracker.loc_detail})")
                active = False
        elif not untrusted and untrusted_since is not None:
            log.info("localization tracking again: resuming")
            untrusted_since = None
        if active and pose is not None:
            stale = now - tracker.last_update() > cfg.pose_timeout_s
            if not untrusted and (plan_task is None or plan_task.done()) and nav.plan_due(now):
                plan_task = node.spawn(plan_job(nav.make_request(pose, now)))
            if stale or untrusted:
                vx, vy, wz = 0.0, 0.0, 0.0
                nav.cmd = (0.0, 0.0, 0.0)
            else:
                vx, vy, wz = nav.step(now, pose)
            if nav.localization_request:
                nav.localization_request = False
                node.spawn(request_localization_update())
            pub_cmd.put(m.Twist2D(vx=vx, vy=vy, wz=wz, stamp=now))
            if now >= next_local_pub:
                pub_local.put(path_message(nav.local_plan, now))
                next_local_pub = now + 0.2
            was_active = True
        elif was_active:
            pub_cmd.put(m.Twist2D(stamp=now))
            pub_local.put(path_message(np.zeros((0, 3)), now))
            was_active = False
        for gid, state, err in nav.take_finished():
            log.info("goal %s %s%s", gid, state, f": {err}" if err else "")
        publish_status(force=now >= next_status)
        if now >= next_status:
            next_status = now + 1.0 / cfg.status_frequency_hz
            node.extra_stats["controller"] = {"cycles": rate.cycles, "overruns": rate.overruns}
        await rate.sleep()
    pub_cmd.put(m.Twist2D(stamp=clock.now()))
