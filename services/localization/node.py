"""The localization service: serves the map and runs AMCL on odometry and scans.

Publishes ``map`` (latched: its queryable also answers the ``map`` query), ``pose`` (latched, after each filter update),
``tf/map_odom`` (latched, every scan once localized; the map pose between updates is map_odom ∘ odom) and
``particles`` (throttled). Serves ``localization/initial_pose``, ``localization/global`` and
``localization/nomotion`` (answered once the update ran on a scan, with its pose and map->odom). The odom pose at a
scan's stamp is interpolated from a short odom history. The last pose is saved to
``<state_dir>/localization_pose.json`` and used as the initial pose after a restart.
"""

from __future__ import annotations

import asyncio
import collections
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import msgspec
import numpy as np

from proto import array
from proto.messages import (
    Empty,
    InitialPoseRequest,
    LaserScan,
    LocalizationState,
    LocalizationUpdate,
    Message,
    NoMotionRequest,
    Odometry,
    Pose2D,
    PoseArray,
    PoseWithCovariance,
    Reply,
    Transform2D,
)
from services.common.map_io import FREE, MapError, OccupancyMap, load_map
from services.common.node import Node, TopicPublisher
from services.common.service import ServiceContext
from services.common.service_events import ServiceEventLog
from services.localization.amcl import Amcl, select_beams
from services.localization.config import LocalizationConfig
from services.localization.odom_history import OdomHistory
from services.localization.pose_store import (
    POSE_FILE,
    SavedPoseIgnored,
    read_saved_pose,
    should_save,
    write_pose,
)
from services.localization.scan_queue import ScanQueue
from services.localization.settle import AtRestSettler

Pose = tuple[float, float, float]

#: wall-clock seconds ``localization/nomotion`` waits for a scan to run the update on before it answers that none came
#: (and withdraws the request, so that a late scan does not move the estimate under a client that judged without it)
NOMOTION_ANSWER_TIMEOUT_S = 3.0


def _finite(*values: float) -> bool:
    return all(math.isfinite(v) for v in values)


def _ns(stamp_s: float) -> int:
    """A stamp in integer nanoseconds, as a bag holds it: stamps compared after a record and replay still match."""
    return round(stamp_s * 1e9)


@dataclass
class Outputs:
    """The service's publishers: ``map`` (latched), ``pose`` (latched like amcl_pose), ``tf/map_odom`` (latched),
    ``particles``, the service events of the queries that change the filter."""

    map: TopicPublisher
    pose: TopicPublisher
    tf: TopicPublisher
    particles: TopicPublisher
    #: query -> its ``<query>/_service_event`` publisher (services/common/service_events.py), never dropped
    events: dict[str, TopicPublisher]

    @classmethod
    def declare(cls, node: Node) -> Outputs:
        events = {"localization/nomotion": node.publisher("localization/nomotion/_service_event", block=True),
                  "localization/initial_pose": node.publisher("localization/initial_pose/_service_event", block=True),
                  "localization/global": node.publisher("localization/global/_service_event", block=True)}
        return cls(node.publisher("map", latched=True), node.publisher("pose", latched=True),
                   node.publisher("tf/map_odom", latched=True), node.publisher("particles"), events)


class LocalizationNode:
    """Wires the map and the AMCL core to Zenoh (all callbacks run on the event loop)."""

    def __init__(self, ctx: ServiceContext, cfg: LocalizationConfig, *, outputs: Outputs | None = None) -> None:
        """``outputs``: publishers shared with the mapping mode (made here when None). The mode switcher
        (``mapping.ModeSwitcher``) subscribes to the sensors and serves the queries, and calls ``on_*`` here."""
        self.ctx = ctx
        self.cfg = cfg
        self.node = ctx.node
        self.log = ctx.node.log
        self.grid: OccupancyMap | None = None
        self.amcl: Amcl | None = None
        self.map_problem = ""
        self.odom = OdomHistory(cfg.odom_history_s)
        self.scans: ScanQueue[LaserScan] = ScanQueue(cfg.scan_queue_size)  # waiting for the odom of their stamp
        self.last_particles_at = -math.inf
        self.stats: dict[str, Any] = collections.Counter()  # counts, and the last verdict and reason
        self.initialised = False
        self.settler = AtRestSettler()
        self._update_waiters: list[asyncio.Future[LocalizationUpdate]] = []  # localization/nomotion queries
        self._reported_converged = False  # localizing until the estimate settled (no-motion updates at rest)
        self.pose_file = Path(cfg.state_dir) / POSE_FILE if cfg.state_dir else None
        outputs = outputs or Outputs.declare(self.node)
        self.pub_map, self.pub_pose, self.pub_tf, self.pub_particles = (
            outputs.map, outputs.pose, outputs.tf, outputs.particles)
        self.pub_events = outputs.events
        self.events = {query: ServiceEventLog() for query in outputs.events}
        #: requests that took effect, waiting for the first scan the filter runs on (their response_sent event)
        self._awaiting_scan: list[tuple[str, int, Reply]] = []
        #: a localization/nomotion request waits until this scan (queued when it came) has been through the filter
        self._update_after: LaserScan | None = None
        #: initial poses to set just before the filter runs on the first scan stamped at or after their stamp (ns)
        self._at_scan: list[tuple[int, int, InitialPoseRequest, Reply]] = []  # (ns, sequence, ...)
        self._last_scan_ns: int | None = None  # the stamp of the last scan the filter ran on
        #: a localization/nomotion request for the first scan stamped at or after this (ns)
        self._nomotion_at_ns: int | None = None
        self._load_map()
        self._initialise()
        self.node.extra_stats["localization"] = self.stats

    # ------------------------------------------------------------------ map and start-up

    def _load_map(self) -> None:
        if not self.cfg.map_yaml:
            self.map_problem = "no map: set localization.map_yaml"
            self.log.error("%s; AMCL is idle", self.map_problem)
            return
        try:
            self.grid = load_map(self.cfg.map_yaml)
            self.amcl = Amcl(self.grid, self.cfg.amcl_params())
        except (MapError, ValueError) as exc:
            self.map_problem = str(exc)
            self.log.error("cannot use the map: %s; AMCL is idle", exc)
            return
        self.pub_map.put(self.grid.to_msg(stamp=self.ctx.clock.now()))
        counts = self.grid.counts()
        self.log.info("map %s: %d x %d cells at %g m, %d free; serving it on `map`", self.cfg.map_yaml,
                      self.grid.width, self.grid.height, self.grid.resolution, counts["free"])

    def _initialise(self) -> None:
        if self.amcl is None:
            return
        cfg = self.cfg
        saved = self._read_saved_pose() if cfg.initialize_at_saved_pose else None
        if saved is not None:
            pose, cov = saved
            self.amcl.set_initial_pose(pose, cov)
            self.log.info("starting at the saved pose (%.3f, %.3f, %.3f)", *pose)
        elif cfg.set_initial_pose:
            pose = (cfg.initial_pose_x, cfg.initial_pose_y, cfg.initial_pose_yaw)
            self.amcl.set_initial_pose(pose, np.diag([cfg.initial_cov_xx, cfg.initial_cov_yy, cfg.initial_cov_aa]))
            self.log.info("starting at the configured initial pose (%.3f, %.3f, %.3f)", *pose)
        else:
            self.initialised = False
            self.log.info("waiting for localization/initial_pose or localization/global")
            return
        self._localizing_from(pose)

    def _localizing_from(self, pose: Pose | None) -> None:
        """The filter was (re)initialised: localizing until it settles; the start pose is published at once with
        the covariance it really has, so that consumers have a pose (and know not to trust it yet)."""
        assert self.amcl is not None
        self.initialised = True
        self.settler.restart()
        if pose is not None:
            cov = self.amcl.pf.estimate().covariance
            self._put_pose(self.ctx.clock.now(), pose, cov)

    def readiness(self) -> str | None:
        """What readiness rests on (docs/readiness.md), or None while the map and filter are not in hand."""
        if self.amcl is None:
            return None
        if not self.initialised:
            return "map loaded; waiting for localization/initial_pose or localization/global"
        return "map loaded, filter initialised"

    def _read_saved_pose(self) -> tuple[Pose, np.ndarray] | None:
        if self.pose_file is None:
            return None
        try:
            return read_saved_pose(self.pose_file, self.cfg.map_yaml)
        except SavedPoseIgnored as exc:
            self.log.log(exc.level, "%s", exc)
            return None

    def save_pose(self) -> None:
        """Write the current estimate to the state folder (no-op without one, or while the filter does not trust
        it: pose_store.py)."""
        amcl = self.amcl
        if self.pose_file is None or amcl is None or amcl.estimate is None \
                or not should_save(amcl.state, amcl.estimate is not None):
            return
        try:
            write_pose(self.pose_file, self.cfg.map_yaml, amcl.estimate.pose, amcl.estimate.covariance,
                       self.ctx.clock.now())
        except OSError as exc:
            self.stats["pose_save_errors"] += 1
            self.log.warning("cannot save the pose to %s: %s", self.pose_file, exc)

    # ------------------------------------------------------------------ sensors

    def on_odom(self, msg: Odometry) -> None:
        p = msg.pose
        if not _finite(msg.stamp, p.x, p.y, p.theta):
            self.stats["bad_odom"] += 1
            return
        last = self.odom.poses[-1] if self.odom.poses else None
        if last is not None and math.hypot(p.x - last[0], p.y - last[1]) > self.cfg.odom_jump_m:
            # drive restarted (odometry back at zero) or was reset: keep the particles, re-anchor on the new odom
            self.stats["odom_jumps"] += 1
            self.log.warning("odometry jumped from (%.2f, %.2f) to (%.2f, %.2f); re-anchoring AMCL on it",
                             last[0], last[1], p.x, p.y)
            self.odom = OdomHistory(self.cfg.odom_history_s)
            self.scans.clear()
            self._request_update_now()
            if self.amcl is not None:
                self.amcl.reanchor_odometry()
        self.odom.add(msg.stamp, (p.x, p.y, p.theta))
        for scan in self.scans.ready(self.odom.latest_stamp):
            self._process(scan)

    def on_scan(self, msg: LaserScan) -> None:
        self.stats["scans"] += 1
        if self.amcl is None or not (self.initialised or self._at_scan):
            return
        if self.odom.latest_stamp is None:
            self.stats["scans_without_odom"] += 1
            return
        for scan in self.scans.push(msg):  # the odom stalled: place within the tolerance, or drop
            self.stats["scans_past_queue"] += 1
            self._process(scan)
        for scan in self.scans.ready(self.odom.latest_stamp):
            self._process(scan)

    def _process(self, scan: LaserScan) -> None:
        self._apply_due(_ns(scan.stamp))
        self._last_scan_ns = _ns(scan.stamp)
        if not self.initialised:
            return
        self._run_filter(scan)
        if scan is self._update_after:  # the last scan taken before a localization/nomotion request
            self._request_update_now()

    def _request_update_now(self) -> None:
        """A deferred ``localization/nomotion`` request takes effect: on the next scan the filter runs on."""
        if self._update_after is not None and self.amcl is not None:
            self._update_after = None
            self.amcl.request_nomotion_update(refine=True)

    def _run_filter(self, scan: LaserScan) -> None:
        assert self.amcl is not None
        odom_pose = self.odom.at(scan.stamp, self.cfg.scan_odom_tolerance_s)
        if odom_pose is None:
            self.stats["scans_out_of_odom_history"] += 1
            return
        try:
            ranges = array(scan, "ranges")
        except Exception as exc:  # a malformed byte field: count it, keep going
            self.stats["bad_scans"] += 1
            self.log.warning("dropping a malformed scan: %s", exc)
            return
        if not _finite(scan.angle_min, scan.angle_increment, scan.range_min, scan.range_max) or ranges.size < 2:
            self.stats["bad_scans"] += 1
            return
        beams = select_beams(ranges, scan.angle_min, scan.angle_increment, scan.range_min, scan.range_max,
                             self.amcl.params)
        if beams.ranges.size < 3:
            self.stats["scans_without_returns"] += 1
            return
        if self.cfg.laser_mount_from_scan:
            mount = (scan.mount.x, scan.mount.y, scan.mount.theta)
            if not _finite(*mount):
                self.stats["bad_scans"] += 1
                return
        else:
            r = self.ctx.robot
            mount = (r.laser_mount_x_m, r.laser_mount_y_m, r.laser_mount_theta_rad)
        dense = None
        if self.amcl.refine_pending:  # every valid beam, for the refinement at rest
            dense = select_beams(ranges, scan.angle_min, scan.angle_increment, scan.range_min, scan.range_max,
                                 self.amcl.params, max_beams=ranges.size)
        asked = self.amcl.refine_pending
        before = self.amcl.state
        self._served_on_scan(scan.stamp)
        updated = self.settler.process(self.amcl, odom_pose, beams, mount, scan.stamp, dense)
        changed = self.amcl.state != before
        if changed:
            self._on_verdict(before)
        if updated:
            self.stats["filter_updates"] += 1
        pose = None
        if (updated or changed) and self.amcl.estimate is not None:
            pose = self._publish_pose(scan.stamp)
        tf = self._publish_tf(scan.stamp)
        self._publish_particles()
        if asked and not self.amcl.refine_pending:  # the requested update (and refinement) ran on this scan
            self._answer_update(pose, tf)

    def _on_verdict(self, before: str) -> None:
        """Log and count a change of the filter's verdict (published with the next pose, sent at once)."""
        assert self.amcl is not None
        a = self.amcl
        self.stats[f"became_{a.state}"] += 1
        self.stats["state"] = a.state
        self.stats["reason"] = a.reason
        if a.state == "lost":
            self.log.warning("localization lost (was %s): %s", before, a.reason)
        else:
            self.log.info("localization %s (was %s): %s", a.state, before, a.reason)

    # ------------------------------------------------------------------ outputs

    def _publish_pose(self, stamp: float) -> PoseWithCovariance:
        assert self.amcl is not None and self.amcl.estimate is not None
        est = self.amcl.estimate
        return self._put_pose(stamp, est.pose, est.covariance)

    def _put_pose(self, stamp: float, pose: Pose, covariance: np.ndarray) -> PoseWithCovariance:
        x, y, th = (float(v) for v in pose)
        a = self.amcl
        assert a is not None
        # the filter's verdict, held at localizing until the estimate has also settled at rest (settle.py)
        state = "localizing" if a.state == "tracking" and not self.settler.converged else a.state
        spread = a.spread_m if math.isfinite(a.spread_m) else -1.0
        u = a.uncertainty
        msg = PoseWithCovariance(stamp=stamp, frame="map", pose=Pose2D(x=x, y=y, theta=th),
                                 covariance=covariance.reshape(-1).tolist(), state=cast(LocalizationState, state),
                                 match_score=a.match_score, spread_m=spread, position_std_m=u.position_std_m(),
                                 weakest_axis_rad=u.weakest_axis_rad(), heading_std_rad=u.heading_std_rad())
        self.pub_pose.put(msg)
        self.stats["state"] = state
        self.stats["reason"] = a.reason
        self.stats["match_score"] = round(a.match_score, 3)
        if state == "tracking" and not self._reported_converged:
            self.log.info("converged at (%.3f, %.3f, %.3f), spread %.3f m, after %d no-motion updates", x, y, th,
                          spread, self.settler.updates)
        self._reported_converged = state == "tracking"
        return msg

    def _publish_tf(self, stamp: float) -> Transform2D | None:
        assert self.amcl is not None
        if self.amcl.map_odom is None:
            return None
        x, y, th = self.amcl.map_odom
        msg = Transform2D(stamp=stamp, parent="map", child="odom", x=x, y=y, theta=th)
        self.pub_tf.put(msg)
        return msg

    def _answer_update(self, pose: PoseWithCovariance | None, tf: Transform2D | None) -> None:
        """Answer every waiting ``localization/nomotion`` with the update just published (pose and map->odom)."""
        assert self.amcl is not None
        waiters, self._update_waiters = self._update_waiters, []
        if pose is None or tf is None:
            answer = LocalizationUpdate(ok=False, message="the update ran but the filter has no estimate")
        else:
            answer = LocalizationUpdate(ok=True, message=f"updated without motion and refined ({pose.state})",
                                        pose=pose, map_odom=tf)
        for fut in waiters:
            if not fut.done():
                fut.set_result(answer)

    def _publish_particles(self) -> None:
        assert self.amcl is not None
        hz = self.cfg.particles_publish_hz
        now = self.ctx.clock.now()
        if hz <= 0 or now - self.last_particles_at < 1.0 / hz:
            return
        self.last_particles_at = now
        pf = self.amcl.pf
        self.pub_particles.put(PoseArray(stamp=now, frame="map", poses=pf.poses[:pf.n].astype("<f4").tobytes(),
                                         weights=pf.weights[:pf.n].astype("<f4").tobytes()))

    # ------------------------------------------------------------------ queries

    def _no_map(self) -> Reply | None:
        if self.amcl is None:
            return Reply(ok=False, message=f"localization has no map ({self.map_problem})")
        return None

    def on_initial_pose(self, req: InitialPoseRequest) -> Reply:
        """Set the initial pose, at once or (``at_scan_stamp``) just before the filter runs on that scan; one that
        took effect (or was scheduled) is published as service events (a replay issues it again)."""
        problem = self._initial_pose_problem(req)
        if problem is not None:
            return problem
        if req.stamp <= 0:  # given now: scans taken before now predate it, also when it is applied later
            req = msgspec.structs.replace(req, stamp=self.ctx.clock.now())
        at_ns = _ns(req.at_scan_stamp) if req.at_scan_stamp > 0 else None
        if at_ns is not None and (self._last_scan_ns is None or at_ns > self._last_scan_ns):
            p = req.pose
            reply = Reply(ok=True, message=f"initial pose ({p.x:.3f}, {p.y:.3f}, {p.theta:.3f}) will be set on the "
                                           f"scan stamped {req.at_scan_stamp:.9f} s")
            self._at_scan.append((at_ns, self._took_effect("localization/initial_pose", req), req, reply))
            self._at_scan.sort(key=lambda item: item[:2])
            return reply
        if at_ns is not None:  # that scan went through the filter already: now, as close to it as there is
            self.stats["initial_poses_late"] += 1
            self.log.warning("initial pose for the scan stamped %.9f s came after it: set now", req.at_scan_stamp)
        reply = self._set_initial_pose(req)
        if reply.ok:
            self._awaiting_scan.append(("localization/initial_pose",
                                        self._took_effect("localization/initial_pose", req), reply))
        return reply

    def _apply_due(self, scan_ns: int) -> None:
        """Set the scheduled initial poses whose scan (the first stamped at or after theirs) is ``scan_ns``, just
        before the filter runs on it; the scan answers them (response_sent)."""
        if self._nomotion_at_ns is not None and self._nomotion_at_ns <= scan_ns and self.amcl is not None:
            self._nomotion_at_ns = None
            self.amcl.request_nomotion_update(refine=True)
        while self._at_scan and self._at_scan[0][0] <= scan_ns:
            _, sequence, req, scheduled = self._at_scan.pop(0)
            reply = self._set_initial_pose(req)
            self._awaiting_scan.append(("localization/initial_pose", sequence, reply if not reply.ok else scheduled))

    def _initial_pose_problem(self, req: InitialPoseRequest) -> Reply | None:
        """Why ``req`` cannot be used (a refusal naming it), or None."""
        if (problem := self._no_map()) is not None:
            return problem
        assert self.grid is not None
        p = req.pose
        if not _finite(p.x, p.y, p.theta):
            return Reply(ok=False, message=f"initial pose ({p.x}, {p.y}, {p.theta}) is not finite")
        if req.covariance and (len(req.covariance) != 9 or not _finite(*req.covariance)):
            return Reply(ok=False, message="covariance must be 9 finite numbers (3x3 over x, y, theta)")
        if not math.isfinite(req.at_scan_stamp) or req.at_scan_stamp < 0:
            return Reply(ok=False, message=f"at_scan_stamp {req.at_scan_stamp} must be 0 (now) or a scan stamp (s)")
        if not math.isfinite(req.stamp) or req.stamp < 0:
            return Reply(ok=False, message=f"stamp {req.stamp} must be 0 (now) or a time on the robot's clock (s)")
        col, row = self.grid.world_to_cell(np.array([p.x]), np.array([p.y]))
        if not (0 <= int(col[0]) < self.grid.width and 0 <= int(row[0]) < self.grid.height):
            return Reply(ok=False, message=f"initial pose ({p.x:.3f}, {p.y:.3f}) lies outside the map")
        return None

    def _set_initial_pose(self, req: InitialPoseRequest) -> Reply:
        if (problem := self._initial_pose_problem(req)) is not None:
            return problem
        assert self.amcl is not None and self.grid is not None
        p = req.pose
        if req.covariance:
            cov = np.asarray(req.covariance, dtype=float).reshape(3, 3)
        else:
            cfg = self.cfg
            cov = np.diag([cfg.initial_cov_xx, cfg.initial_cov_yy, cfg.initial_cov_aa])
        try:
            self.amcl.set_initial_pose((p.x, p.y, p.theta), cov,
                                       stamp_s=req.stamp if req.stamp > 0 else self.ctx.clock.now())
        except ValueError as exc:
            return Reply(ok=False, message=str(exc))
        self._localizing_from((p.x, p.y, p.theta))
        col, row = self.grid.world_to_cell(np.array([p.x]), np.array([p.y]))
        note = "" if self.grid.data[int(row[0]), int(col[0])] == FREE else " (note: that cell is not free in the map)"
        self.log.info("initial pose set to (%.3f, %.3f, %.3f)%s", p.x, p.y, p.theta, note)
        return Reply(ok=True, message=f"initial pose set to ({p.x:.3f}, {p.y:.3f}, {p.theta:.3f}){note}")

    def on_global(self, _req: Empty) -> Reply:
        if (problem := self._no_map()) is not None:
            return problem
        assert self.amcl is not None
        self.amcl.global_localization(stamp_s=self.ctx.clock.now())
        self._localizing_from(None)
        self.log.info("global localization: %d particles over free space", self.amcl.pf.n)
        reply = Reply(ok=True, message=f"global localization started with {self.amcl.pf.n} particles")
        self._awaiting_scan.append(("localization/global", self._took_effect("localization/global", _req), reply))
        return reply

    async def on_nomotion(self, req: NoMotionRequest) -> LocalizationUpdate:
        """Update the filter without motion on the next scan (``at_scan_stamp``: on that scan), refine at rest, and
        answer with the result once it is published (``NOMOTION_ANSWER_TIMEOUT_S`` at most: then the request is
        withdrawn and the answer says so)."""
        if (problem := self._no_map()) is not None:
            return LocalizationUpdate(ok=False, message=problem.message)
        assert self.amcl is not None
        if not self.initialised:
            return LocalizationUpdate(ok=False,
                                      message="not localized yet: set an initial pose or start global localization")
        if not math.isfinite(req.at_scan_stamp) or req.at_scan_stamp < 0:
            return LocalizationUpdate(ok=False, message=f"at_scan_stamp {req.at_scan_stamp} must be 0 (the next "
                                                        f"scan) or a scan stamp (s)")
        at_ns = _ns(req.at_scan_stamp) if req.at_scan_stamp > 0 else None
        if at_ns is not None and (self._last_scan_ns is None or at_ns > self._last_scan_ns):
            self._nomotion_at_ns = at_ns  # that scan may still be on its way, or wait in the queue
        elif len(self.scans):  # the waiting scans were taken before the request: it runs on one received after it
            self._update_after = self.scans.waiting[-1]
        else:
            self.amcl.request_nomotion_update(refine=True)
        # recorded, so that a replay of the recording issues the request again (service_events.py)
        sequence = self._took_effect("localization/nomotion", req)
        answer = await self._await_update()
        served_on = ("scan", answer.pose.stamp) if answer.ok and answer.pose is not None else ("", 0.0)
        self.pub_events["localization/nomotion"].put(ServiceEventLog.response_sent(
            self.ctx.clock.now(), sequence, answer, *served_on))
        return answer

    def _took_effect(self, query: str, req: Message) -> int:
        """Publish the ``request_received`` event of a request that has just changed the filter; its sequence."""
        event = self.events[query].request_received(self.ctx.clock.now(), req)
        self.pub_events[query].put(event)
        return event.sequence

    def _served_on_scan(self, stamp: float) -> None:
        """The filter runs on the scan stamped ``stamp``: the requests that took effect before it were served on it."""
        for query, sequence, reply in self._awaiting_scan:
            self.pub_events[query].put(ServiceEventLog.response_sent(self.ctx.clock.now(), sequence, reply, "scan",
                                                                     stamp))
        self._awaiting_scan.clear()

    async def _await_update(self) -> LocalizationUpdate:
        """The answer of the update just requested, or that none came within ``NOMOTION_ANSWER_TIMEOUT_S``."""
        assert self.amcl is not None
        fut: asyncio.Future[LocalizationUpdate] = asyncio.get_running_loop().create_future()
        self._update_waiters.append(fut)
        try:
            return await asyncio.wait_for(asyncio.shield(fut), NOMOTION_ANSWER_TIMEOUT_S)
        except TimeoutError:
            if fut.done():  # answered in the same turn of the loop as the deadline passed
                return fut.result()
            if fut in self._update_waiters:
                self._update_waiters.remove(fut)
            if not self._update_waiters and self.amcl is not None:
                self._update_after = None
                self._nomotion_at_ns = None
                self.amcl.withdraw_nomotion_request()
            return LocalizationUpdate(ok=False, message=f"no scan reached the filter within "
                                                        f"{NOMOTION_ANSWER_TIMEOUT_S:g} s: the update is withdrawn")
