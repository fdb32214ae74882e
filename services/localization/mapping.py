"""Mapping mode of the localization service (live graph SLAM) and the runtime switch between mapping and AMCL.

``run(ctx)`` owns the service's sensors, publishers and queries and hands them to the active mode:
- mapping (``MappingNode``): every ``odom``/``scan`` pair past the motion gates goes through ``LiveMapper`` (scan
  matching against the recent keyframes, keyframes, loop closures, graph optimisation). Publishes ``pose`` (latched,
  per processed scan), ``tf/map_odom`` (latched, every scan) and the growing ``map`` (latched, every
  ``map_publish_period_s``).
- navigation: ``LocalizationNode`` (map server + AMCL), fed by this dispatcher.
Queries: ``localization/save_map`` {name} writes ``<name>.yaml`` + ``<name>.pgm`` (ROS map_server trinary) and
``<name>.trajectory.txt`` (every scan's pose, as ``zagv map build`` writes it) into the maps folder and replies with
the YAML path; ``localization/mode`` {mode, map_yaml} switches: to mapping (a new map
whose frame starts at the current pose), or to navigation on ``map_yaml`` (the name of a map in the maps folder,
never a path; empty: the last saved map), starting AMCL at the current pose. ``initial_pose``/``global``/
``nomotion`` are answered by AMCL (refused while mapping).
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from proto import array
from proto.messages import (
    MAP_NAME,
    LaserScan,
    LocalizationUpdate,
    ModeRequest,
    NoMotionRequest,
    Odometry,
    Pose2D,
    PoseWithCovariance,
    Reply,
    SaveMapRequest,
    Transform2D,
)
from services.common.map_io import MapError, OccupancyMap, load_map
from services.common.service import ServiceContext
from services.localization.config import LocalizationConfig
from services.localization.node import LocalizationNode, Outputs
from services.localization.odom_history import OdomHistory
from services.localization.scan_queue import ScanQueue
from services.localization.slam.live import LiveMapper
from services.localization.slam.map_files import FREE_THRESH, OCCUPIED_THRESH, write_ros_map, write_trajectory
from services.localization.slam.mapper import SlamConfig, scan_to_points
from services.localization.slam.occupancy import OccupancyGrid

#: odometry kept in synchronous mode (bag s): Zenoh hands each topic to the loop from its own thread, so under load
#: the odom of a scan may arrive well after the scan (or the scans after their odom); every scan still finds its odom
SYNC_ODOM_HISTORY_S = 60.0
#: scans that may wait for their odom in synchronous mode (about a minute of a 5-10 Hz lidar)
SYNC_SCANS_WAITING = 600

#: covariance reported with SLAM poses (x, y: (2 cm)^2; theta: (1°)^2)
SLAM_COVARIANCE = [4e-4, 0.0, 0.0, 0.0, 4e-4, 0.0, 0.0, 0.0, 3e-4]


def grid_to_map(grid: OccupancyGrid) -> OccupancyMap:
    """Log-odds grid -> int8 OccupancyMap (100 occupied, 0 free, -1 unknown) with map_saver's thresholds."""
    p = grid.probability()
    data = np.full(p.shape, -1, np.int8)
    data[p > OCCUPIED_THRESH] = 100
    data[p < FREE_THRESH] = 0
    ox, oy = (float(v) for v in grid.origin_xy_m)
    return OccupancyMap(data, float(grid.resolution_m), (ox, oy, 0.0))


class MappingNode:
    """Live SLAM on the event loop: odom history, scan -> points, ``LiveMapper``, outputs."""

    def __init__(self, ctx: ServiceContext, cfg: LocalizationConfig, outputs: Outputs,
                 start_pose: tuple[float, float, float]) -> None:
        self.ctx = ctx
        self.cfg = cfg
        self.out = outputs
        self.log = ctx.node.log
        slam = SlamConfig(odom_prior_sigma_xy_m=cfg.mapping_odom_sigma_xy_m,
                          odom_prior_sigma_theta_rad=cfg.mapping_odom_sigma_theta_rad)
        self.mapper = LiveMapper(slam, start_pose=start_pose, min_travel_m=cfg.mapping_min_travel_m,
                                 min_turn_rad=cfg.mapping_min_turn_rad)
        self.odom = OdomHistory(max(cfg.odom_history_s, SYNC_ODOM_HISTORY_S) if cfg.mapping_sync
                                else cfg.odom_history_s)
        self.pending_scan: LaserScan | None = None
        # synchronous mode: scans wait, in order, for the odom that passes their stamp (tf2's MessageFilter)
        self.waiting_scans: ScanQueue[LaserScan] = ScanQueue(SYNC_SCANS_WAITING)
        self._newest_scan: LaserScan | None = None
        self._inbox: collections.deque[Odometry | LaserScan] = collections.deque()  # mapping_sync
        self._drain_scheduled = False
        self.stats: dict[str, float] = {"scans": 0, "processed": 0, "skipped": 0, "bad_scans": 0,
                                        "keyframes": 0, "loop_closures": 0, "loop_closures_rejected": 0,
                                        "scan_match_fallbacks": 0, "cpu_ms_per_processed_scan": 0.0,
                                        "cpu_ms_max": 0.0, "render_ms": 0.0}
        self._cpu_total_s = 0.0
        self._map_published_at = -math.inf
        self._map_dirty = False
        self.last_map: OccupancyMap | None = None

    @property
    def pose(self) -> tuple[float, float, float] | None:
        if self.mapper.map_odom is None or not self.odom.poses:
            return None
        p = self.mapper.pose_at(np.array(self.odom.poses[-1]))
        assert p is not None
        return float(p[0]), float(p[1]), float(p[2])

    def on_odom(self, msg: Odometry) -> None:
        if self.cfg.mapping_sync:
            self._enqueue(msg)
            return
        self._take_odom(msg)

    def _take_odom(self, msg: Odometry) -> None:
        p = msg.pose
        if not all(math.isfinite(v) for v in (msg.stamp, p.x, p.y, p.theta)):
            self.stats["bad_odom"] = self.stats.get("bad_odom", 0) + 1
            return
        self.odom.add(msg.stamp, (p.x, p.y, p.theta))
        if self.pending_scan is not None and msg.stamp >= self.pending_scan.stamp:
            scan, self.pending_scan = self.pending_scan, None
            self._process(scan)

    def on_scan(self, msg: LaserScan) -> None:
        """Keeps only the newest scan and handles it once the event loop has delivered what was queued before it:
        when mapping falls behind (a loaded machine, a keyframe with a loop search), older scans are dropped
        instead of queueing up. With ``mapping_sync`` every scan is handled, in order (a replayed log)."""
        self.stats["scans"] += 1
        if self.cfg.mapping_sync:
            self._enqueue(msg)
            return
        if self._newest_scan is not None:
            self.stats["dropped_behind"] = self.stats.get("dropped_behind", 0) + 1
        else:
            asyncio.get_running_loop().call_soon(self._take_newest_scan)
        self._newest_scan = msg

    def _enqueue(self, msg: Odometry | LaserScan) -> None:
        """Synchronous mode: odom and scans are handled in arrival order, at most one scan per turn of the event
        loop (its timers and the liveness heartbeat run in between however long the backlog grows)."""
        self._inbox.append(msg)
        self.stats["sync_backlog_max"] = max(self.stats.get("sync_backlog_max", 0), len(self._inbox))
        if not self._drain_scheduled:
            self._drain_scheduled = True
            asyncio.get_running_loop().call_soon(self._drain)

    def _drain(self) -> None:
        """Synchronous mode, one turn of the loop: take odom in arrival order until one scan has been processed."""
        processed = self._process_ready_scan()
        while not processed and self._inbox:
            msg = self._inbox.popleft()
            if isinstance(msg, LaserScan):
                for scan in self.waiting_scans.push(msg):  # the odom stalled: the oldest go with the tolerance
                    self._process(scan)
                    processed = True
                processed = self._process_ready_scan() or processed
            else:
                self._take_odom(msg)
                processed = self._process_ready_scan()
        self._drain_scheduled = bool(self._inbox) or self.waiting_scans.has_ready(self.odom.latest_stamp)
        if self._drain_scheduled:
            asyncio.get_running_loop().call_soon(self._drain)

    def _process_ready_scan(self) -> bool:
        """Synchronous mode: process the oldest waiting scan once the odom covers its stamp."""
        scan = self.waiting_scans.pop_ready(self.odom.latest_stamp)
        if scan is None:
            return False
        self._process(scan)
        return True

    def _take_newest_scan(self) -> None:
        msg, self._newest_scan = self._newest_scan, None
        if msg is not None:
            self._handle_scan(msg)

    def _handle_scan(self, msg: LaserScan) -> None:
        if self.pending_scan is not None:
            scan, self.pending_scan = self.pending_scan, None
            self._process(scan)
        latest = self.odom.latest_stamp
        if latest is None:
            return
        if msg.stamp > latest:
            self.pending_scan = msg
            return
        self._process(msg)

    def _points(self, scan: LaserScan) -> tuple[np.ndarray, np.ndarray] | None:
        try:
            ranges = array(scan, "ranges").astype(float)
        except Exception as exc:  # a malformed byte field: count it, keep going
            self.log.warning("dropping a malformed scan: %s", exc)
            return None
        if self.cfg.laser_mount_from_scan:
            mount = np.array([scan.mount.x, scan.mount.y, scan.mount.theta])
        else:
            r = self.ctx.robot
            mount = np.array([r.laser_mount_x_m, r.laser_mount_y_m, r.laser_mount_theta_rad])
        if not np.all(np.isfinite(mount)) or ranges.size < 2 or not all(
                math.isfinite(v) for v in (scan.angle_min, scan.angle_increment, scan.range_min, scan.range_max)):
            return None
        angles = scan.angle_min + scan.angle_increment * np.arange(ranges.size)
        points = scan_to_points(ranges, angles, mount, min_range_m=max(scan.range_min, 0.05),
                                max_range_m=scan.range_max)
        return points, mount[:2]

    def _process(self, scan: LaserScan) -> None:
        odom_pose = self.odom.at(scan.stamp, self.cfg.scan_odom_tolerance_s)
        if odom_pose is None:
            self.stats["scans_out_of_odom_history"] = self.stats.get("scans_out_of_odom_history", 0) + 1
            return
        odom = np.array(odom_pose)
        if self.mapper.moved_enough(odom):
            converted = self._points(scan)
            if converted is None or len(converted[0]) < 20:
                self.stats["bad_scans"] += 1
                return
            cpu0 = time.thread_time()  # CPU time of the mapping work itself, for the stats (not robot timing)
            self.mapper.add_scan(scan.stamp, odom, *converted)
            cpu = time.thread_time() - cpu0
            self._cpu_total_s += cpu
            s = self.stats
            s["processed"] = self.mapper.processed
            s["keyframes"] = self.mapper.slam.n_keyframes
            s["loop_closures"] = len(self.mapper.slam.loop_closures)
            s["loop_closures_rejected"] = len(self.mapper.slam.rejected_closures)
            s["scan_match_fallbacks"] = self.mapper.slam.fallback_matches
            s["cpu_ms_per_processed_scan"] = round(1e3 * self._cpu_total_s / self.mapper.processed, 2)
            s["cpu_ms_max"] = round(max(s["cpu_ms_max"], 1e3 * cpu), 2)
            self._map_dirty = True
            self._publish_pose(scan.stamp)
        else:
            self.mapper.note_skipped(scan.stamp, odom)
            self.stats["skipped"] = self.mapper.skipped
        self._publish_tf(scan.stamp)
        self.maybe_publish_map()

    def _publish_pose(self, stamp: float) -> None:
        p = self.mapper.pose
        if p is None:
            return
        slam = self.mapper.slam
        # a scan that failed the match-quality gate was placed by odometry: report the odometry's spread
        covariance = SLAM_COVARIANCE if slam.last_match_ok else [float(v) for v in slam.match_covariance().ravel()]
        self.out.pose.put(PoseWithCovariance(stamp=stamp, frame="map",
                                             pose=Pose2D(x=float(p[0]), y=float(p[1]), theta=float(p[2])),
                                             covariance=covariance))

    def _publish_tf(self, stamp: float) -> None:
        m = self.mapper.map_odom
        if m is not None:
            self.out.tf.put(Transform2D(stamp=stamp, parent="map", child="odom", x=float(m[0]), y=float(m[1]),
                                        theta=float(m[2])))

    def current_map(self) -> OccupancyGrid | None:
        return self.mapper.render()

    def maybe_publish_map(self, force: bool = False) -> None:
        now = self.ctx.clock.now()
        if not self._map_dirty or (not force and now - self._map_published_at < self.cfg.map_publish_period_s):
            return
        t0 = time.thread_time()
        grid = self.current_map()
        if grid is None:
            return
        self.last_map = grid_to_map(grid)
        self.out.map.put(self.last_map.to_msg(stamp=now))
        self.stats["render_ms"] = round(1e3 * (time.thread_time() - t0), 1)
        self.stats["full_renders"] = self.mapper.full_renders
        self._map_published_at = now
        self._map_dirty = False


class ModeSwitcher:
    """Dispatches the service's inputs and queries to the active mode and switches modes on request."""

    def __init__(self, ctx: ServiceContext, cfg: LocalizationConfig) -> None:
        self.ctx = ctx
        self.cfg = cfg
        self.node = ctx.node
        self.log = ctx.node.log
        self.out = Outputs.declare(self.node)
        self.nav: LocalizationNode | None = None
        self.mapping: MappingNode | None = None
        self.last_saved: Path | None = None
        if cfg.mode == "mapping":
            self._start_mapping((cfg.initial_pose_x, cfg.initial_pose_y, cfg.initial_pose_yaw))
        else:
            self.nav = LocalizationNode(ctx, cfg, outputs=self.out)
        self.node.subscribe("odom", self.on_odom)
        self.node.subscribe("scan", self.on_scan)
        self.node.queryable("localization/initial_pose", self._amcl_query(lambda n, r: n.on_initial_pose(r)))
        self.node.queryable("localization/global", self._amcl_query(lambda n, r: n.on_global(r)))
        self.node.queryable("localization/nomotion", self.on_nomotion)
        self.node.queryable("localization/save_map", self.on_save_map)
        self.node.queryable("localization/mode", self.on_mode)

    def readiness(self) -> str | None:
        """What readiness rests on (docs/readiness.md): mapping needs no input; navigation its map and filter."""
        if self.mapping is not None:
            return "mapping mode"
        return self.nav.readiness() if self.nav is not None else None

    @property
    def mode(self) -> str:
        return "mapping" if self.mapping is not None else "navigation"

    @property
    def maps_dir(self) -> Path | None:
        if self.cfg.maps_dir:
            return Path(self.cfg.maps_dir)
        return Path(self.cfg.state_dir) / "maps" if self.cfg.state_dir else None

    def _start_mapping(self, start_pose: tuple[float, float, float]) -> None:
        self.mapping = MappingNode(self.ctx, self.cfg, self.out, start_pose)
        self.node.extra_stats["mapping"] = self.mapping.stats
        self.log.info("mapping: a new map starting at (%.3f, %.3f, %.3f)", *start_pose)

    def current_pose(self) -> tuple[float, float, float] | None:
        if self.mapping is not None:
            return self.mapping.pose
        if self.nav is not None and self.nav.amcl is not None and self.nav.amcl.estimate is not None:
            x, y, th = self.nav.amcl.estimate.pose
            return float(x), float(y), float(th)
        return None

    # ------------------------------------------------------------------ inputs

    def on_odom(self, msg: Odometry) -> None:
        if self.mapping is not None:
            self.mapping.on_odom(msg)
        elif self.nav is not None:
            self.nav.on_odom(msg)

    def on_scan(self, msg: LaserScan) -> None:
        if self.mapping is not None:
            self.mapping.on_scan(msg)
        elif self.nav is not None:
            self.nav.on_scan(msg)

    def tick(self) -> None:
        """Periodic work: save AMCL's pose."""
        if self.nav is not None:
            self.nav.save_pose()

    # ------------------------------------------------------------------ queries

    def _amcl_query(self, call: Callable[[LocalizationNode, Any], Reply]) -> Callable[[Any], Reply]:
        def handler(req: Any) -> Reply:
            if self.nav is None:
                return Reply(ok=False, message="localization is mapping; switch to navigation first")
            return call(self.nav, req)
        return handler

    async def on_nomotion(self, req: NoMotionRequest) -> LocalizationUpdate:
        if self.nav is None:
            return LocalizationUpdate(ok=False, message="localization is mapping; switch to navigation first")
        return await self.nav.on_nomotion(req)

    def on_save_map(self, req: SaveMapRequest) -> Reply:
        if self.mapping is None:
            return Reply(ok=False, message="not mapping: nothing to save (start mapping with localization/mode)")
        if not MAP_NAME.match(req.name or ""):
            return Reply(ok=False, message=f"map name {req.name!r} must be 1-64 letters, digits, '_', '-' or '.' "
                                           "(no path, not starting with '.' or '-')")
        folder = self.maps_dir
        if folder is None:
            return Reply(ok=False, message="no maps folder: set localization.maps_dir or localization.state_dir")
        grid = self.mapping.current_map()
        if grid is None:
            return Reply(ok=False, message="no map yet: no scan has been processed")
        try:
            path = write_ros_map(grid, folder, req.name).resolve()
            write_trajectory(folder / f"{req.name}.trajectory.txt", *self.mapping.mapper.trajectory())
        except OSError as exc:
            return Reply(ok=False, message=f"cannot write the map into {folder}: {exc}")
        self.last_saved = path
        self.log.info("map saved to %s", path)
        return Reply(ok=True, message=str(path))

    def _resolve_map(self, name: str) -> Path:
        """The map a ``localization/mode`` request names: a map in the maps folder, chosen by name (``name`` or
        ``name.yaml``), never by path; empty: the map saved last, else the configured one. Raises MapError."""
        if not name:
            if self.last_saved is not None:
                return self.last_saved
            if self.cfg.map_yaml:
                return Path(self.cfg.map_yaml)
            raise MapError("navigation needs a map: give a map name or save a map first")
        stem = name[:-5] if name.endswith(".yaml") else name
        if not MAP_NAME.match(stem):
            shown = repr(name[:80]) + ("..." if len(name) > 80 else "")
            raise MapError(f"map {shown} is not a map name: 1-64 letters, digits, '_', '-' or '.', no path "
                           "(maps are chosen by name from the maps folder)")
        if self.maps_dir is None:
            raise MapError("no maps folder: set localization.maps_dir or localization.state_dir")
        path = self.maps_dir / f"{stem}.yaml"
        if not path.exists():
            raise MapError(f"no map named {stem!r} in the maps folder")
        return path

    def on_mode(self, req: ModeRequest) -> Reply:
        pose = self.current_pose()
        if req.mode == "mapping":
            start = pose if pose is not None else (self.cfg.initial_pose_x, self.cfg.initial_pose_y,
                                                   self.cfg.initial_pose_yaw)
            self.tick()
            self.nav = None
            self._start_mapping(start)
            return Reply(ok=True, message=f"mapping: a new map starting at ({start[0]:.3f}, {start[1]:.3f}, "
                                          f"{start[2]:.3f})")
        try:
            path = self._resolve_map(req.map_yaml)
            load_map(path)
        except MapError as exc:
            return Reply(ok=False, message=f"cannot navigate: {exc}")
        # a map in the maps folder was built from scans: its walls' surfaces lie inside their first layer of cells
        changes: dict = {"map_yaml": str(path), "mode": "navigation", "map_surface": "cell"}
        if pose is not None:  # the saved map shares the mapping frame: AMCL starts where SLAM left the robot
            changes.update(initial_pose_x=pose[0], initial_pose_y=pose[1], initial_pose_yaw=pose[2],
                           set_initial_pose=True, initialize_at_saved_pose=False,
                           initial_cov_xx=0.01, initial_cov_yy=0.01, initial_cov_aa=0.003)
        nav_cfg = msgspec.structs.replace(self.cfg, **changes)
        self.mapping = None
        self.node.extra_stats.pop("mapping", None)
        self.nav = LocalizationNode(self.ctx, nav_cfg, outputs=self.out)
        where = "" if pose is None else f" from ({pose[0]:.3f}, {pose[1]:.3f}, {pose[2]:.3f})"
        self.log.info("navigation on %s%s", path, where)
        return Reply(ok=True, message=f"navigation on {path}{where}")


async def run(ctx: ServiceContext) -> None:
    cfg: LocalizationConfig = ctx.config["localization"]
    switcher = ModeSwitcher(ctx, cfg)
    ctx.node.spawn(ctx.node.ready_when(switcher.readiness, ctx.stop))
    period = 1.0 / cfg.save_pose_rate if cfg.save_pose_rate > 0 else 1.0
    while not ctx.stop.is_set():
        stop = asyncio.ensure_future(ctx.stop.wait())
        sleeper = asyncio.ensure_future(ctx.clock.sleep(min(period, max(cfg.map_publish_period_s, 0.1))))
        await asyncio.wait({stop, sleeper}, return_when=asyncio.FIRST_COMPLETED)
        for task in (stop, sleeper):
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        if switcher.mapping is not None:
            switcher.mapping.maybe_publish_map()
        elif cfg.save_pose_rate > 0:
            switcher.tick()
    switcher.tick()

