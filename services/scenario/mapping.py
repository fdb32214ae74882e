"""The mapping phase of ``zagv scenario run`` (a scenario's ``[mapping]`` table): the paper's workflow of jogging the
robot around with SLAM running, saving the map and navigating on it.

The simulated operator jogs the route by publishing ``cmd_vel`` while watching ``sim/ground_truth`` (as a person
watches the robot): towards each waypoint it drives straight at ``jog_speed_mps`` (slowing as
``v = min(speed, kp_xy * distance)`` near it) and turns at ``wz = kp_yaw * heading error``, all within the Table 2
box; a waypoint counts when within ``WAYPOINT_XY_M`` / ``WAYPOINT_YAW_RAD``. Before driving, every leg of the route is
checked against the ground-truth map for the chassis' clearance, so a route through a wall is refused with its leg
named instead of ending in a collision. Then ``localization/save_map`` saves the map, the map is scored against the
ground truth (occupied-cell F1 of ``services.localization.slam.map_compare`` on the visible wall surface, after a
±2-cell alignment search), ``localization/mode`` switches localization to AMCL on the saved map, and the phase waits
until nav's global costmap follows the re-published ``map`` (same geometry, every occupied cell lethal).
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from proto import codec
from proto import messages as m
from services.common.robot import RobotSpec
from services.common.se2 import rotate, wrap_angle

if TYPE_CHECKING:
    from services.scenario.client import Client

Pose = tuple[float, float, float]

WAYPOINT_XY_M = 0.1
WAYPOINT_YAW_RAD = 0.1
KP_XY = 1.0  # 1/s: the approach speed near a waypoint is its distance per second
KP_YAW = 1.5  # 1/s
CLEARANCE_MARGIN_M = 0.1  # route clearance beyond the chassis radius (the jog is not exact)
COMMAND_PERIOD_S = 0.05  # sim s between cmd_vel messages (drive stops after its cmd_timeout_s, 0.2 s)
LATE_COMMAND_S = 0.2  # the drive's default cmd_timeout_s: a command later than this found the robot stopping
TRUTH_TIMEOUT_S = 10.0  # wall s without ground truth before the jog gives up (the sim died)


# --------------------------------------------------------------------------- the operator (pure)


def jog_command(pose: Pose, target: Pose, spec: RobotSpec, speed_mps: float, *, kp_xy: float = KP_XY,
                kp_yaw: float = KP_YAW) -> tuple[float, float, float]:
    """Body twist (vx, vy m/s, wz rad/s) that moves ``pose`` along the straight line to ``target``.

    World error (dx, dy) -> body (bx, by) = R(-theta) (dx, dy); speed ``v = min(speed_mps, kp_xy * |b|)`` along it,
    scaled down as a whole (direction kept) to fit ``vx_min..vx_max`` and ``|vy| <= vy_max``; ``wz = kp_yaw *
    wrap_angle(target_theta - theta)`` clamped to ``wz_max``.
    """
    dx, dy = target[0] - pose[0], target[1] - pose[1]
    bx, by = rotate(-pose[2], dx, dy)
    dist = math.hypot(bx, by)
    vx = vy = 0.0
    if dist > 1e-9:
        v = min(speed_mps, kp_xy * dist)
        vx, vy = v * bx / dist, v * by / dist
        limit_x = spec.vx_max_mps if vx > 0 else -spec.vx_min_mps
        scale = min(1.0, limit_x / abs(vx) if abs(vx) > 1e-12 else 1.0,
                    spec.vy_max_mps / abs(vy) if abs(vy) > 1e-12 else 1.0)
        vx, vy = vx * scale, vy * scale
    wz = kp_yaw * wrap_angle(target[2] - pose[2])
    return spec.twist_limits().clamp(vx, vy, wz)


def arrived(pose: Pose, target: Pose, xy_m: float = WAYPOINT_XY_M, yaw_rad: float = WAYPOINT_YAW_RAD) -> bool:
    return (math.hypot(target[0] - pose[0], target[1] - pose[1]) < xy_m
            and abs(wrap_angle(target[2] - pose[2])) < yaw_rad)


def route_length_m(start: Pose, route: list[Pose]) -> float:
    """Length of the polyline start -> waypoints (m)."""
    pts = np.array([start[:2]] + [w[:2] for w in route], dtype=float)
    return float(np.hypot(*np.diff(pts, axis=0).T).sum())


def route_clearance_problems(start: Pose, route: list[Pose], solid: np.ndarray, resolution_m: float,
                             origin_xy_m: tuple[float, float], radius_m: float, step_m: float = 0.05) -> list[str]:
    """Legs of the route whose straight line comes closer than ``radius_m`` to a solid cell (``solid[row, col]``,
    row 0 at the origin; outside the grid counts as solid). Distances are from the point to the nearest solid cell's
    edge (the centre distance less half a cell, less another half for the point's own cell)."""
    from scipy import ndimage

    clearance = ndimage.distance_transform_edt(~solid) * resolution_m - resolution_m
    problems = []
    points = [start] + list(route)
    for k in range(1, len(points)):
        a, b = np.asarray(points[k - 1][:2]), np.asarray(points[k][:2])
        n = max(2, int(math.ceil(np.hypot(*(b - a)) / step_m)) + 1)
        xy = a + np.linspace(0.0, 1.0, n)[:, None] * (b - a)
        col = np.floor((xy[:, 0] - origin_xy_m[0]) / resolution_m).astype(int)
        row = np.floor((xy[:, 1] - origin_xy_m[1]) / resolution_m).astype(int)
        inside = (row >= 0) & (col >= 0) & (row < solid.shape[0]) & (col < solid.shape[1])
        d = np.full(n, -1.0)
        d[inside] = clearance[row[inside], col[inside]]
        worst = int(np.argmin(d))
        if d[worst] < radius_m:
            where = "outside the map" if d[worst] < 0 else f"{max(d[worst], 0.0):.2f} m from a wall"
            problems.append(f"leg {k} ({points[k - 1][0]:.2f}, {points[k - 1][1]:.2f}) -> ({points[k][0]:.2f}, "
                            f"{points[k][1]:.2f}) passes ({xy[worst, 0]:.2f}, {xy[worst, 1]:.2f}), {where} (the "
                            f"chassis needs {radius_m:.2f} m)")
    return problems


def costmap_follows(costmap: m.OccupancyGrid, grid: Any) -> str:
    """Why nav's published global costmap does not (yet) follow the map ``grid`` (an ``OccupancyMap``): '' when its
    geometry is the map's and every occupied map cell is lethal (100) in it."""
    if abs(costmap.resolution - grid.resolution) > 1e-9 or (costmap.width, costmap.height) != (grid.width,
                                                                                             grid.height):
        return (f"costmap {costmap.width} x {costmap.height} at {costmap.resolution:g} m, map {grid.width} x "
                f"{grid.height} at {grid.resolution:g} m")
    if max(abs(costmap.origin.x - grid.origin[0]), abs(costmap.origin.y - grid.origin[1])) > grid.resolution / 2:
        return f"costmap origin ({costmap.origin.x:.3f}, {costmap.origin.y:.3f}), map origin {grid.origin[:2]}"
    cost = codec.array(costmap, "data").reshape(costmap.height, costmap.width)
    missing = int(np.count_nonzero((grid.data >= 65) & (cost != 100)))
    return f"{missing} occupied map cells are not lethal in the costmap" if missing else ""


# --------------------------------------------------------------------------- the phase (async shell)


@dataclass
class MappingResult:
    route_length_m: float
    driven_m: float
    jog_time_s: float  # sim
    jog_wall_s: float
    map_yaml: str
    map_f1: dict[str, Any]
    nav_map_wait_s: float  # wall
    late_commands: int = 0

    def to_json(self) -> dict[str, Any]:
        return {"route_length_m": round(self.route_length_m, 3), "driven_m": round(self.driven_m, 3),
                "jog_time_s": round(self.jog_time_s, 3), "jog_wall_s": round(self.jog_wall_s, 3),
                "map_yaml": self.map_yaml, "map_f1": self.map_f1, "nav_map_wait_s": round(self.nav_map_wait_s, 3),
                "late_jog_commands": self.late_commands}

    def line(self) -> str:
        f = self.map_f1
        return (f"mapping: route {self.route_length_m:.1f} m (driven {self.driven_m:.1f} m) in {self.jog_time_s:.0f} s"
                f" sim ({self.jog_wall_s:.0f} s wall); map {self.map_yaml}; occupied-cell F1 {f['f1']:.3f} (precision"
                f" {f['precision']:.3f}, recall {f['recall']:.3f}, offset {f['offset_xy_m'][0]:+.2f}, "
                f"{f['offset_xy_m'][1]:+.2f} m) against the ground truth")


def map_agreement(built_yaml: str | Path, truth_yaml: str | Path) -> dict[str, Any]:
    """Occupied-cell F1 of a built map against the ground-truth map (solid = not free, as the simulator treats it):
    the truth's visible wall surface, recall only where the built map saw free space nearby, ±2-cell alignment."""
    from services.common.map_io import FREE, load_map
    from services.localization.slam.map_compare import best_aligned_f1, surface

    built, truth = load_map(built_yaml), load_map(truth_yaml)
    truth_walls = surface(truth.data != FREE, truth.data == FREE)
    r = best_aligned_f1(built.data >= 65, built.resolution, built.origin[:2], truth_walls, truth.resolution,
                        truth.origin[:2], search_cells=2, built_free=built.data == FREE)
    return {"precision": round(r.precision, 4), "recall": round(r.recall, 4), "f1": round(r.f1, 4),
            "built_occupied": r.built_occupied, "truth_occupied": r.truth_occupied,
            "offset_xy_m": [round(r.offset_xy_m[0], 3), round(r.offset_xy_m[1], 3)]}


def check_route(start: Pose, route: list[Pose], truth_yaml: str | Path, spec: RobotSpec) -> None:
    """RuntimeError naming every leg of the route that does not keep the chassis clear of the ground-truth walls."""
    from services.common.map_io import FREE, load_map

    truth = load_map(truth_yaml)
    problems = route_clearance_problems(start, route, truth.data != FREE, truth.resolution, truth.origin[:2],
                                        spec.chassis_radius_m + CLEARANCE_MARGIN_M)
    if problems:
        raise RuntimeError("the mapping route is not clear of the walls: " + "; ".join(problems))


@dataclass
class JogStats:
    driven_m: float = 0.0
    time_s: float = 0.0  # sim
    commands: int = 0
    late_commands: int = 0  # sent more than LATE_COMMAND_S (sim) after the previous one: drive may have stopped
    max_gap_s: float = 0.0  # sim


async def jog(c: Client, route: list[Pose], spec: RobotSpec, speed_mps: float, progress=print) -> JogStats:
    """Drive the route by ``cmd_vel``. RuntimeError on a collision or a waypoint not reached within a generous
    sim-time allowance. Commands that come late (the sim outruns this process) are counted in the stats."""
    pub = c.session.declare_publisher(c.keys("cmd_vel"))
    t_start = c.sim_time
    stats = JogStats()
    driven = 0.0
    assert c.truth is not None
    last_xy = (c.truth.pose.x, c.truth.pose.y)
    sent_at = -math.inf
    c.jogging = True
    try:
        for k, target in enumerate(route, 1):
            p = c.truth.pose
            need_s = math.hypot(target[0] - p.x, target[1] - p.y) / speed_mps \
                + abs(wrap_angle(target[2] - p.theta)) / spec.wz_max_radps
            deadline = c.sim_time + 3.0 * need_s + 30.0
            while True:
                c.truth_changed.clear()
                try:
                    await asyncio.wait_for(c.truth_changed.wait(), TRUTH_TIMEOUT_S)
                except TimeoutError:
                    raise RuntimeError(f"no sim/ground_truth for {TRUTH_TIMEOUT_S:.0f} s while jogging") from None
                gt = c.truth
                p = gt.pose
                driven += math.hypot(p.x - last_xy[0], p.y - last_xy[1])
                last_xy = (p.x, p.y)
                pose = (p.x, p.y, p.theta)
                if gt.collided:
                    raise RuntimeError(f"the robot collided while jogging to waypoint {k} {target}, at "
                                       f"({p.x:.2f}, {p.y:.2f}, {p.theta:.2f})")
                if arrived(pose, target):
                    break
                if c.sim_time > deadline:
                    raise RuntimeError(f"waypoint {k} {target} not reached within {deadline - t_start:.0f} s (sim) "
                                       f"of jogging: at ({p.x:.2f}, {p.y:.2f}, {p.theta:.2f})")
                if gt.stamp - sent_at >= COMMAND_PERIOD_S:
                    vx, vy, wz = jog_command(pose, target, spec, speed_mps)
                    pub.put(codec.encode(m.Twist2D(stamp=gt.stamp, vx=vx, vy=vy, wz=wz)))
                    if math.isfinite(sent_at):
                        gap = gt.stamp - sent_at
                        stats.max_gap_s = max(stats.max_gap_s, gap)
                        stats.late_commands += gap > LATE_COMMAND_S
                    stats.commands += 1
                    sent_at = gt.stamp
            progress(f"scenario: mapping: waypoint {k}/{len(route)} ({target[0]:.2f}, {target[1]:.2f}, "
                     f"{target[2]:.2f}) at {c.sim_time - t_start:.0f} s")
        pub.put(codec.encode(m.Twist2D(stamp=c.sim_time)))
        await c.sim_sleep(1.0)  # come to rest: the last scans reach the map
    finally:
        c.jogging = False
        pub.put(codec.encode(m.Twist2D(stamp=c.sim_time)))
        pub.undeclare()
    stats.driven_m, stats.time_s = driven, c.sim_time - t_start
    return stats


class NavMapWatch:
    """Watches ``map`` and ``nav/costmap`` (subscribe before switching modes, so the re-published map is seen):
    ``done`` once localization published the saved map (stamp >= ``since``, its geometry and cells) and nav then
    published a global costmap that follows it."""

    def __init__(self, c: Client, saved: Any, since: float) -> None:
        self.saved, self.since = saved, since
        self.map_stamp: float | None = None
        self.why = "the saved map was not re-published on `map`"
        self.done = False
        loop = asyncio.get_running_loop()
        self._subs = []
        for name, cb in (("map", self._on_map), ("nav/costmap", self._on_costmap)):
            def on_sample(sample, cb=cb) -> None:
                try:
                    msg = codec.decode_as(m.OccupancyGrid, sample.payload.to_bytes(), str(sample.key_expr))
                except codec.ProtoDecodeError:
                    return
                with contextlib.suppress(RuntimeError):  # the loop already closed
                    loop.call_soon_threadsafe(cb, msg)
            self._subs.append(c.session.declare_subscriber(c.keys(name), on_sample))

    def _on_map(self, msg: m.OccupancyGrid) -> None:
        if msg.stamp < self.since:
            return
        saved = self.saved
        if (msg.width, msg.height) == (saved.width, saved.height) and np.array_equal(
                codec.array(msg, "data").reshape(msg.height, msg.width), saved.data):
            self.map_stamp = msg.stamp
            self.why = "nav published no costmap after the saved map"
        else:
            self.why = f"a {msg.width} x {msg.height} map that is not the saved one was published"

    def _on_costmap(self, msg: m.OccupancyGrid) -> None:
        if self.map_stamp is None or msg.stamp <= self.map_stamp:
            return
        self.why = costmap_follows(msg, self.saved)
        self.done = not self.why

    async def wait(self, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        while not self.done:
            if time.monotonic() > deadline:
                raise RuntimeError(f"nav did not take up the saved map within {timeout_s:.0f} s: {self.why}")
            await asyncio.sleep(0.05)

    def close(self) -> None:
        for s in self._subs:
            with contextlib.suppress(Exception):
                s.undeclare()


async def run_mapping(c: Client, start: Pose, route: list[Pose], save_as: str, speed_mps: float,
                      truth_yaml: str | Path, spec: RobotSpec, progress=print) -> MappingResult:
    """The whole phase: check the route, jog it, save the map, score it, navigate on it (module docstring)."""
    from services.common.map_io import load_map
    from services.scenario.client import wait_until

    check_route(start, route, truth_yaml, spec)
    await wait_until(lambda: c.map_odom is not None, "localization (mapping) published no tf/map_odom", 90.0)
    progress(f"scenario: mapping: jogging {len(route)} waypoints ({route_length_m(start, route):.1f} m) at "
             f"{speed_mps:.2f} m/s")
    wall0 = time.monotonic()
    stats = await jog(c, route, spec, speed_mps, progress)
    jog_wall, jog_s = time.monotonic() - wall0, stats.time_s
    if stats.late_commands:
        progress(f"scenario: mapping: {stats.late_commands} of {stats.commands} jog commands came more than "
                 f"{LATE_COMMAND_S} s (sim) after the previous one (longest gap {stats.max_gap_s:.2f} s): the sim runs "
                 "faster than this machine keeps up with; a lower `speed` jogs more smoothly")
    saved = await c.query("localization/save_map", m.SaveMapRequest(name=save_as), timeout_s=30.0)
    if not saved.ok:
        raise RuntimeError(f"localization/save_map refused: {saved.message}")
    map_yaml = saved.message
    f1 = map_agreement(map_yaml, truth_yaml)
    progress(f"scenario: mapping: saved {map_yaml} after {jog_s:.0f} s (sim) of jogging; occupied-cell F1 "
             f"{f1['f1']:.3f} against the ground truth")
    wall1 = time.monotonic()
    watch = NavMapWatch(c, load_map(map_yaml), since=c.sim_time - 0.25)  # localization's clock may trail ours
    try:
        mode = await c.query("localization/mode", m.ModeRequest(mode="navigation", map_yaml=save_as),
                             timeout_s=30.0)
        if not mode.ok:
            raise RuntimeError(f"localization/mode refused navigation on {map_yaml}: {mode.message}")
        await watch.wait(timeout_s=60.0)
    finally:
        watch.close()
    progress(f"scenario: mapping: {mode.message}; nav follows the saved map")
    return MappingResult(route_length_m(start, route), stats.driven_m, jog_s, jog_wall, map_yaml, f1,
                         time.monotonic() - wall1, stats.late_commands)
