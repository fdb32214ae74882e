"""``zagv scenario run FILE [--json OUT] [--plots DIR]``: run navigation goals in the simulator and report the
final-pose errors against ground truth (the paper's Table 3).

Scenario TOML (keys fixed):

    world = "corridor"            # a built-in sim world, or
    map = "maps/depot.yaml"       # any ROS map YAML (relative to the scenario file, else to the current folder)
    start = [0.0, 0.0, 0.0]       # x, y (m), theta (rad)
    repeats = 10
    speed = 4.0                   # sim speed factor (sim s per wall s)
    name = "corridor_table3"      # optional (default: the file name without .toml); description = "..." optional
    [[goals]]
    pose = [3.0, 0.1, 1.57]
    id = "1"                      # optional
    [[dynamic_obstacles]]
    rect = [9.0, 1.6, 10.0, 3.0]  # xmin, ymin, xmax, ymax (m)
    during_goal = 7               # 1-based index of the goal during whose leg it appears (removed after the leg)
    appear_after_s = 5.0          # sim seconds after that goal is sent
    [mapping]                     # optional: build the map first by jogging, then run the goals on it
    route = [[4.0, 0.1, 0.0], [4.0, 0.1, 3.1]]  # waypoints [x, y, theta] jogged in order from `start` (world frame)
    save_as = "corridor_built"    # optional map name (default "<name>_built"): letters, digits, '_', '-', '.'
    jog_speed_mps = 0.2           # optional, > 0 and <= the robot's vx_max_mps and vy_max_mps (default: vx_max_mps)

The stack runs headless on its own free ports. Each repeat starts with the robot teleported to ``start`` and the
localization told so. A goal counts as reached when nav reports ``succeeded``; the error is the ground-truth pose
0.5 s (sim) after nav's result, minus the target, theta wrapped to (-pi, pi]. A goal counts as reached when that
ground-truth error is within the robot's goal tolerance (Table 2: 0.05 m, 0.05 rad), whatever nav claimed; a goal
nav reports ``succeeded`` outside it is printed and counted. JSON: ``{"runs": [{"run": 1, "goals": [{"id",
"target", "reached", "claimed", "nav_error", "final", "error", "time_s", "recoveries", "collisions", "driven_m",
"loc_error_max_m", "loc_error_rms_m"}]}]}`` (localization error: |estimate - truth| at every odometry stamp of the
leg, the truth interpolated to that stamp).

With ``[mapping]`` (the paper's mapping workflow, services/cli/scenario_mapping.py) the stack starts in mapping mode
(``zagv up --mapping``, SLAM's map frame and the simulated robot both at ``start``); the simulated operator jogs the
route by ``cmd_vel`` while watching ``sim/ground_truth``, then the map is saved (``localization/save_map``), scored
against the world's ground-truth map (occupied-cell F1), localization switches to AMCL on it (``localization/mode``)
and, once nav's costmap follows the saved map, the goals run as above. The JSON gains ``"mapping": {"route_length_m",
"driven_m", "jog_time_s", "jog_wall_s", "map_yaml", "map_f1": {"precision", "recall", "f1", ...}, "nav_map_wait_s",
"late_jog_commands"}`` (jog commands sent more than the drive's 0.2 s command timeout after the previous one: the sim
ran faster than the machine kept up with).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import math
import re
import sys
import tempfile
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from proto import codec
from proto import messages as m
from proto.keys import Keys
from services.common.query import QueryError, query

TERMINAL = ("succeeded", "failed", "canceled")


def wrap(a: float) -> float:
    """Angle wrapped to (-pi, pi]."""
    return -((-a + math.pi) % (2 * math.pi) - math.pi)


# --------------------------------------------------------------------------- scenario file


@dataclass
class Goal:
    id: str
    pose: tuple[float, float, float]


@dataclass
class DynamicObstacle:
    rect: tuple[float, float, float, float]
    during_goal: int
    appear_after_s: float


@dataclass
class Mapping:
    """The ``[mapping]`` table: the jog route, the saved map's name and the jog speed."""

    route: list[tuple[float, float, float]]
    save_as: str
    jog_speed_mps: float


@dataclass
class Scenario:
    goals: list[Goal]
    world: str | None = None
    map_yaml: str | None = None
    start: tuple[float, float, float] = (0.0, 0.0, 0.0)
    repeats: int = 1
    speed: float = 1.0
    dynamic_obstacles: list[DynamicObstacle] = field(default_factory=list)
    name: str = "scenario"
    mapping: Mapping | None = None
    #: several robots in one world, each with its own start and goals (services/cli/scenario_fleet.py)
    robots: list[Any] = field(default_factory=list)


class ScenarioError(ValueError):
    """A scenario file that cannot be run; the message names the key."""


def _pose(v: Any, what: str) -> tuple[float, float, float]:
    if not (isinstance(v, list) and len(v) == 3 and all(isinstance(x, int | float) for x in v)):
        raise ScenarioError(f"{what} must be [x, y, theta] numbers, got {v!r}")
    if not all(math.isfinite(x) for x in v):
        raise ScenarioError(f"{what} must be finite, got {v!r}")
    return (float(v[0]), float(v[1]), float(v[2]))


def _mapping(raw: Any, p: Path, name: str) -> Mapping:
    from services.common.robot import RobotSpec

    if not isinstance(raw, dict):
        raise ScenarioError(f"{p}: mapping must be a table ([mapping]), got {raw!r}")
    extra = sorted(set(raw) - {"route", "save_as", "jog_speed_mps"})
    if extra:
        raise ScenarioError(f"{p}: mapping: unknown key(s) {', '.join(extra)}; known: jog_speed_mps, route, save_as")
    route_raw = raw.get("route")
    if not isinstance(route_raw, list) or not route_raw:
        raise ScenarioError(f"{p}: mapping.route must be a non-empty list of [x, y, theta] waypoints, got "
                            f"{route_raw!r}")
    route = [_pose(w, f"mapping.route[{k}]") for k, w in enumerate(route_raw, 1)]
    default_name = re.sub(r"[^A-Za-z0-9_.-]", "_", name)[:57].lstrip(".-") or "scenario"
    save_as = raw.get("save_as", f"{default_name}_built")
    if not isinstance(save_as, str) or not m.MAP_NAME.match(save_as):
        raise ScenarioError(f"{p}: mapping.save_as {save_as!r} must be a map name of 1-64 letters, digits, '_', '-' "
                            "or '.' (no path, not starting with '.' or '-')")
    spec = RobotSpec()
    limit = min(spec.vx_max_mps, spec.vy_max_mps)
    speed = raw.get("jog_speed_mps", spec.vx_max_mps)
    if isinstance(speed, bool) or not isinstance(speed, int | float) or not 0 < speed <= limit:
        raise ScenarioError(f"{p}: mapping.jog_speed_mps must be a number in (0, {limit:g}] (the robot's vx_max_mps "
                            f"and vy_max_mps), got {speed!r}")
    return Mapping(route, save_as, float(speed))


def load_scenario(path: str | Path) -> Scenario:
    p = Path(path)
    try:
        data = tomllib.loads(p.read_text())
    except OSError as exc:
        raise ScenarioError(f"{p}: cannot read: {exc.strerror or exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ScenarioError(f"{p}: TOML syntax error: {exc}") from None
    known = {"world", "map", "start", "repeats", "speed", "goals", "dynamic_obstacles", "name", "description",
             "mapping", "robots"}
    unknown = sorted(set(data) - known)
    if unknown:
        raise ScenarioError(f"{p}: unknown key(s) {', '.join(unknown)}; known: {', '.join(sorted(known))}")
    if ("world" in data) == ("map" in data):
        raise ScenarioError(f"{p}: give exactly one of `world` (built-in name) or `map` (ROS map YAML)")
    map_yaml = None
    if "map" in data:
        mp = Path(data["map"])
        candidates = [mp] if mp.is_absolute() else [(p.parent / mp).resolve(), mp.resolve()]
        found = [c for c in candidates if c.is_file()]
        if not found:
            raise ScenarioError(f"{p}: map {data['map']} not found (relative to the scenario file or the current"
                                f" folder: {', '.join(map(str, candidates))})")
        map_yaml = str(found[0])
    goals_raw = data.get("goals", [])
    robots = []
    if "robots" in data:
        from services.cli.scenario_fleet import load_robots

        if goals_raw or "mapping" in data or "dynamic_obstacles" in data:
            raise ScenarioError(f"{p}: with [[robots]], goals go in each robot's [[robots.goals]] (no top-level "
                                "goals, mapping or dynamic_obstacles)")
        robots = load_robots(data["robots"], p)
    elif not goals_raw:
        raise ScenarioError(f"{p}: no [[goals]]")
    goals = parse_goals(goals_raw, p, "goals")
    obstacles = []
    for k, o in enumerate(data.get("dynamic_obstacles", []), 1):
        extra = sorted(set(o) - {"rect", "during_goal", "appear_after_s"})
        if extra:
            raise ScenarioError(f"{p}: dynamic_obstacles[{k}]: unknown key(s) {', '.join(extra)}")
        rect = o.get("rect")
        if not (isinstance(rect, list) and len(rect) == 4 and rect[0] < rect[2] and rect[1] < rect[3]):
            raise ScenarioError(f"{p}: dynamic_obstacles[{k}].rect must be [xmin, ymin, xmax, ymax], got {rect!r}")
        during = int(o.get("during_goal", 1))
        if not 1 <= during <= len(goals):
            raise ScenarioError(f"{p}: dynamic_obstacles[{k}].during_goal {during} is not a goal index 1..{len(goals)}")
        obstacles.append(DynamicObstacle(tuple(float(v) for v in rect), during, float(o.get("appear_after_s", 0.0))))
    repeats = int(data.get("repeats", 1))
    speed = float(data.get("speed", 1.0))
    if repeats < 1 or not speed > 0:
        raise ScenarioError(f"{p}: repeats must be >= 1 and speed > 0")
    name = data.get("name", p.stem)
    if not isinstance(name, str) or not name:
        raise ScenarioError(f"{p}: name must be a non-empty string, got {name!r}")
    mapping = _mapping(data["mapping"], p, name) if "mapping" in data else None
    return Scenario(goals, data.get("world"), map_yaml, _pose(data.get("start", [0.0, 0.0, 0.0]), "start"), repeats,
                    speed, obstacles, name, mapping, robots)


def parse_goals(goals_raw: Any, p: Path, what: str) -> list[Goal]:
    """``[[goals]]`` entries (``pose``, optional ``id``) -> Goals; ScenarioError naming ``what[k]``."""
    if not isinstance(goals_raw, list):
        raise ScenarioError(f"{p}: {what} must be an array of tables, got {goals_raw!r}")
    goals = []
    for k, g in enumerate(goals_raw, 1):
        if not isinstance(g, dict) or "pose" not in g:
            raise ScenarioError(f"{p}: {what}[{k}] has no pose")
        extra = sorted(set(g) - {"pose", "id", "paper_mean_error"})
        if extra:
            raise ScenarioError(f"{p}: {what}[{k}]: unknown key(s) {', '.join(extra)}")
        goals.append(Goal(str(g.get("id", k)), _pose(g["pose"], f"{what}[{k}].pose")))
    return goals


# --------------------------------------------------------------------------- results


def summarize(runs: list[dict]) -> list[dict]:
    """Per goal (in order): target, mean error over reached runs, reached count, mean time."""
    rows: dict[str, dict] = {}
    for run in runs:
        for g in run["goals"]:
            r = rows.setdefault(g["id"], {"id": g["id"], "target": g["target"], "errors": [], "times": [],
                                          "reached": 0, "total": 0})
            r["total"] += 1
            if g["reached"]:
                r["reached"] += 1
                r["errors"].append(g["error"])
                r["times"].append(g["time_s"])
    out = []
    for r in rows.values():
        e = np.asarray(r["errors"], dtype=float).reshape(-1, 3)
        out.append({"id": r["id"], "target": r["target"], "reached": r["reached"], "total": r["total"],
                    "mean_error": e.mean(axis=0).tolist() if len(e) else [math.nan] * 3,
                    "mean_abs_error": np.abs(e).mean(axis=0).tolist() if len(e) else [math.nan] * 3,
                    "mean_time_s": float(np.mean(r["times"])) if r["times"] else math.nan})
    return out


def leg_totals(runs: list[dict]) -> dict:
    """Totals over every goal of ``runs``: goals, reached (ground truth), claimed succeeded, claimed succeeded
    outside the tolerance, collisions, recoveries, localization error max and RMS (m, over all samples, RMS
    weighted by leg), time (s) and ground-truth distance driven (m), and time per metre (s/m) of the reached legs."""
    goals = [g for r in runs for g in r["goals"]]
    reached = [g for g in goals if g["reached"]]
    loc_max = [g.get("loc_error_max_m") for g in goals if g.get("loc_error_max_m") is not None]
    loc_rms = [g.get("loc_error_rms_m") for g in goals if g.get("loc_error_rms_m") is not None]
    t = sum(g["time_s"] for g in reached)
    d = sum(g.get("driven_m", 0.0) for g in reached)
    return {"goals": len(goals), "reached": len(reached),
            "claimed": sum(g.get("claimed", "succeeded" if g["reached"] else "") == "succeeded" for g in goals),
            "claimed_outside": sum(g.get("claimed") == "succeeded" and not g["reached"] for g in goals),
            "collisions": sum(g.get("collisions", 0) for g in goals),
            "recoveries": sum(g.get("recoveries", 0) for g in goals),
            "loc_error_max_m": max(loc_max) if loc_max else math.nan,
            "loc_error_rms_m": float(np.sqrt(np.mean(np.square(loc_rms)))) if loc_rms else math.nan,
            "time_s": t, "driven_m": d, "time_per_metre_s": t / d if d > 0 else math.nan}


def format_table(summary: list[dict]) -> str:
    w = max([len(str(r["id"])) for r in summary] + [4])
    head = f"{'goal':>{w}}  {'target (x, y, θ)':<24}  {'mean error x / y / θ':<26}  {'|error| x / y / θ':<26}  " \
           f"{'reached':>8}  {'time s':>7}"
    lines = [head, "-" * len(head)]
    for r in summary:
        t = "({:.2f}, {:.2f}, {:.2f})".format(*r["target"])
        e = "{:+.3f} / {:+.3f} / {:+.3f}".format(*r["mean_error"])
        a = "{:.3f} / {:.3f} / {:.3f}".format(*r["mean_abs_error"])
        lines.append(f"{r['id']:>{w}}  {t:<24}  {e:<26}  {a:<26}  {r['reached']:>3}/{r['total']:<4}  "
                     f"{r['mean_time_s']:>7.1f}")
    return "\n".join(lines)


# --------------------------------------------------------------------------- running


@dataclass
class Leg:
    run: int
    goal: Goal
    start_t: float
    plan: np.ndarray | None = None
    final_plan: np.ndarray | None = None
    obstacles: list[tuple[float, float, float, float]] = field(default_factory=list)
    trace: list[tuple[float, float, float, float, float, float, float]] = field(default_factory=list)
    #: the pose nav drives on (map->odom composed with odometry) at every odometry stamp of the leg: (t, x, y)
    estimates: list[tuple[float, float, float]] = field(default_factory=list)


def localization_errors_m(leg: Leg) -> np.ndarray:
    """|estimate - ground truth| (m) at each estimate's stamp, the truth interpolated between its samples there
    (matched in sim time, so the lag of the messages under load is not counted as error)."""
    tr = np.asarray(leg.trace, dtype=float).reshape(-1, 7)
    est = np.asarray(leg.estimates, dtype=float).reshape(-1, 3)
    if len(tr) < 2 or not len(est):
        return np.zeros(0)
    order = np.argsort(tr[:, 0], kind="stable")
    t, x, y = tr[order, 0], tr[order, 1], tr[order, 2]
    inside = (est[:, 0] >= t[0]) & (est[:, 0] <= t[-1])
    e = est[inside]
    return np.hypot(e[:, 1] - np.interp(e[:, 0], t, x), e[:, 2] - np.interp(e[:, 0], t, y))


def _passes_around(poses: np.ndarray, rects: list[tuple[float, float, float, float]], near_m: float = 1.5) -> bool:
    """Whether a path comes within ``near_m`` of an obstacle but keeps 0.6 m off it (a detour, not a stop)."""
    for x0, y0, x1, y1 in rects:
        dx = np.maximum(np.maximum(x0 - poses[:, 0], poses[:, 0] - x1), 0.0)
        dy = np.maximum(np.maximum(y0 - poses[:, 1], poses[:, 1] - y1), 0.0)
        d = np.hypot(dx, dy)
        if d.min() < near_m and d.min() > 0.6:
            return True
    return False


class Client:
    """What the runner watches: sim clock, ground truth, nav status and path."""

    def __init__(self, session, keys: Keys, loop: asyncio.AbstractEventLoop) -> None:  # noqa: ANN001
        self.session, self.keys, self.loop = session, keys, loop
        self.sim_time = 0.0
        self.truth: m.GroundTruth | None = None
        self.status: m.NavStatus | None = None
        self.status_changed = asyncio.Event()
        self.paths: list[tuple[float, np.ndarray]] = []
        self.odom_count = 0
        self.pose: m.PoseWithCovariance | None = None
        self.pose_count = 0
        self.odom: tuple[float, float, float] | None = None
        self.map_odom: tuple[float, float, float] | None = None
        self.collisions = 0
        self.leg: Leg | None = None
        self.jogging = False  # the mapping phase drives the robot (collisions count then too)
        self.truth_changed = asyncio.Event()
        self.aborted = False
        self.detours: list[bool] = []  # per leg with a dynamic obstacle: whether nav planned around it
        self.localization_errors: list[tuple[float, float, float]] = []
        self._subs = []
        self._sub("clock", m.Clock, self._on_clock)
        self._sub("sim/ground_truth", m.GroundTruth, self._on_truth)
        self._sub("nav/status", m.NavStatus, self._on_status)
        self._sub("nav/path", m.Path, self._on_path)
        self._sub("odom", m.Odometry, self._on_odom)
        self._sub("pose", m.PoseWithCovariance, self._on_pose)
        self._sub("tf/map_odom", m.Transform2D, self._on_tf)

    def _on_odom(self, msg: m.Odometry) -> None:
        self.odom_count += 1
        self.odom = (msg.pose.x, msg.pose.y, msg.pose.theta)
        est = self.estimate()
        if self.leg is not None and est is not None:
            self.leg.estimates.append((msg.stamp, est[0], est[1]))

    def _on_tf(self, msg: m.Transform2D) -> None:
        self.map_odom = (msg.x, msg.y, msg.theta)

    def estimate(self) -> tuple[float, float, float] | None:
        """The robot's pose as nav sees it: map->odom composed with the odometry pose."""
        if self.odom is None or self.map_odom is None:
            return None
        a, b = self.map_odom, self.odom
        c, s = math.cos(a[2]), math.sin(a[2])
        return (a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], wrap(a[2] + b[2]))

    def _on_pose(self, msg: m.PoseWithCovariance) -> None:
        self.pose = msg
        self.pose_count += 1

    def _sub(self, name: str, t: type, cb) -> None:  # noqa: ANN001
        def on_sample(sample) -> None:  # noqa: ANN001
            try:
                msg = codec.decode_as(t, sample.payload.to_bytes(), str(sample.key_expr))
            except codec.ProtoDecodeError:
                return
            with contextlib.suppress(RuntimeError):  # the loop already closed at the end of the run
                self.loop.call_soon_threadsafe(cb, msg)

        self._subs.append(self.session.declare_subscriber(self.keys(name), on_sample))

    def _on_clock(self, msg: m.Clock) -> None:
        self.sim_time = max(self.sim_time, msg.stamp)

    def _on_truth(self, msg: m.GroundTruth) -> None:
        if msg.collided and not (self.truth and self.truth.collided) and (self.leg is not None or self.jogging):
            self.collisions += 1  # while driving a leg (the sim's own start pose may lie in a wall of a map)
        self.truth = msg
        self.sim_time = max(self.sim_time, msg.stamp)
        if self.leg is not None:
            p, v = msg.pose, msg.twist
            self.leg.trace.append((msg.stamp, p.x, p.y, p.theta, v.vx, v.vy, v.wz))
        self.truth_changed.set()

    def _on_status(self, msg: m.NavStatus) -> None:
        self.status = msg
        self.status_changed.set()

    def _on_path(self, msg: m.Path) -> None:
        poses = codec.array(msg, "poses").copy()
        leg = self.leg
        if leg is not None and len(poses):
            if leg.plan is None:
                leg.plan = poses
            elif leg.obstacles and leg.final_plan is None and _passes_around(poses, leg.obstacles):
                leg.final_plan = poses

    async def query(self, name: str, req: m.Message | None = None, timeout_s: float = 5.0) -> Any:
        return await query(self.session, self.keys, name, req, timeout_s=timeout_s)

    async def sim_sleep(self, dt: float) -> None:
        end = self.sim_time + dt
        while self.sim_time < end:
            await asyncio.sleep(0.02)

    def close(self) -> None:
        for s in self._subs:
            with contextlib.suppress(Exception):
                s.undeclare()


async def wait_until(cond, what: str, timeout_s: float) -> None:  # noqa: ANN001
    """Wait (wall time) for ``cond()``; RuntimeError naming ``what`` after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            raise RuntimeError(f"{what} within {timeout_s:.0f} s")
        await asyncio.sleep(0.05)


async def place_robot(c: Client, pose: tuple[float, float, float]) -> None:
    """Teleport the simulated robot and tell localization where it is; wait for the estimate to agree."""
    await wait_until(lambda: c.odom_count > 5, "no odometry (is drive running and its CAN link up?)", 90.0)
    p = m.Pose2D(x=pose[0], y=pose[1], theta=pose[2])
    r = await c.query("sim/teleport", m.TeleportRequest(pose=p))
    if not r.ok:
        raise RuntimeError(f"sim/teleport refused: {r.message}")
    await c.sim_sleep(1.0)  # scans taken before the jump are through the pipeline
    cov = [0.0025, 0, 0, 0, 0.0025, 0, 0, 0, 0.003]
    for attempt in range(1, 7):
        r = await c.query("localization/initial_pose", m.InitialPoseRequest(pose=p, covariance=cov))
        if not r.ok:
            raise RuntimeError(f"localization/initial_pose refused: {r.message}")
        count_at_set = c.pose_count

        def localized(converged: bool) -> bool:  # a pose published after the reset, near the start
            e = c.pose
            return (e is not None and c.pose_count > count_at_set  # noqa: B023
                    and (e.state == "tracking" or not converged)
                    and math.hypot(e.pose.x - pose[0], e.pose.y - pose[1]) < 0.1
                    and abs(wrap(e.pose.theta - pose[2])) < 0.1)

        try:  # localization converges at rest (state "tracking"); a map where it cannot settle keeps the near pose
            with contextlib.suppress(RuntimeError):
                await wait_until(lambda: localized(True), "localization did not converge", 10.0)
            await wait_until(lambda: localized(False), f"localization did not report a pose near the start {pose}",
                             10.0)
            break
        except RuntimeError:
            if attempt == 6:
                raise
    # scans taken between the teleport and the reset were placed with the old pose: not obstacles of this world
    with contextlib.suppress(QueryError):
        await c.query("nav/clear_costmaps", m.Empty())
    await c.sim_sleep(1.0)


def judge_leg(result: dict, state: str, nav_error: str, leg: Leg, collisions: int, xy_tol_m: float,
              yaw_tol_rad: float) -> None:
    """Fill a goal's result: ``reached`` by the ground truth (|error xy| < xy_tol_m and |error theta| <
    yaw_tol_rad), whatever nav ``claimed``; the leg's collisions, recoveries, driven distance (ground truth) and
    the max and RMS of |localization estimate - truth| over the leg (``localization_errors_m``)."""
    result["claimed"] = state
    result["nav_error"] = nav_error
    result["collisions"] = collisions
    e = result["error"]
    result["reached"] = bool(e[0] is not None and math.hypot(e[0], e[1]) < xy_tol_m and abs(e[2]) < yaw_tol_rad)
    tr = np.asarray(leg.trace, dtype=float).reshape(-1, 7)
    result["driven_m"] = round(float(np.hypot(*np.diff(tr[:, 1:3], axis=0).T).sum()), 3) if len(tr) > 1 else 0.0
    le = localization_errors_m(leg)
    if len(le):
        result["loc_error_max_m"] = round(float(le.max()), 4)
        result["loc_error_rms_m"] = round(float(np.sqrt(np.mean(le ** 2))), 4)


async def run_goal(c: Client, sc: Scenario, run: int, index: int, goal: Goal, timeout_s: float,
                   legs: list[Leg] | None, xy_tol_m: float = 0.05, yaw_tol_rad: float = 0.05) -> dict:
    leg = Leg(run, goal, c.sim_time)
    c.leg = leg
    obstacles = [o for o in sc.dynamic_obstacles if o.during_goal == index]
    placed: list[str] = []
    req = m.GoalRequest(pose=m.Pose2D(x=goal.pose[0], y=goal.pose[1], theta=goal.pose[2]),
                        id=f"r{run}g{goal.id}")
    deadline = time.monotonic() + 30.0
    while True:  # a reply lost under load: ask again (the same id, so nav takes it as the same goal)
        try:
            reply: m.GoalReply = await c.query("nav/goal", req)
            break
        except QueryError:
            if time.monotonic() > deadline:
                raise
            await asyncio.sleep(0.5)
    while not reply.accepted and ("no robot pose" in reply.reason or "no map" in reply.reason) \
            and time.monotonic() < deadline:
        await asyncio.sleep(0.2)  # nav has not yet seen odometry, map->odom or the map
        reply = await c.query("nav/goal", req)
    t0 = c.sim_time
    collisions_before = c.collisions
    result = {"id": goal.id, "target": list(goal.pose), "reached": False, "final": [None] * 3,
              "error": [None] * 3, "time_s": 0.0, "claimed": "rejected", "nav_error": reply.reason,
              "recoveries": 0, "collisions": 0, "driven_m": 0.0, "loc_error_max_m": None, "loc_error_rms_m": None}
    if not reply.accepted:
        print(f"scenario: run {run} goal {goal.id} rejected: {reply.reason}", flush=True)
        c.leg = None
        return result
    state, error = "", ""
    try:
        while True:
            for k, o in enumerate(obstacles):
                oid = f"scenario{k}"
                if oid not in placed and c.sim_time - t0 >= o.appear_after_s:
                    rr = await c.query("sim/obstacles", m.ObstacleRequest(action="add", id=oid, rect=list(o.rect)))
                    if rr.ok:
                        placed.append(oid)
                        leg.obstacles.append(o.rect)
                    else:
                        print(f"scenario: obstacle {oid} refused: {rr.message}", flush=True)
                        placed.append(oid)
            st = c.status
            if st is not None and st.goal_id == reply.goal_id and st.state in TERMINAL:
                state, error = st.state, st.error
                result["recoveries"] = st.recoveries
                break
            if c.sim_time - t0 > timeout_s:
                await c.query("nav/cancel", m.CancelRequest(goal_id=reply.goal_id))
                state, error = "timeout", f"no result within {timeout_s:.0f} s (sim)"
                break
            c.status_changed.clear()
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(c.status_changed.wait(), 0.1)
        result["time_s"] = round(c.sim_time - t0, 3)
        await c.sim_sleep(0.5)
        if c.truth is not None:
            p = c.truth.pose
            result["final"] = [p.x, p.y, p.theta]
            result["error"] = [p.x - goal.pose[0], p.y - goal.pose[1], wrap(p.theta - goal.pose[2])]
            est = c.estimate()
            if est is not None:  # how far localization was off at the end (diagnostic, not in the JSON)
                c.localization_errors.append((est[0] - p.x, est[1] - p.y, wrap(est[2] - p.theta)))
        judge_leg(result, state, error, leg, c.collisions - collisions_before, xy_tol_m, yaw_tol_rad)
        if state != "succeeded":
            print(f"scenario: run {run} goal {goal.id}: {state} {error}", flush=True)
        elif not result["reached"]:
            print(f"scenario: run {run} goal {goal.id}: nav reported succeeded but the robot is outside the "
                  f"tolerance ({result['error'][0]:+.3f}, {result['error'][1]:+.3f}, {result['error'][2]:+.3f})",
                  flush=True)
    finally:
        for oid in placed:
            with contextlib.suppress(QueryError):
                await c.query("sim/obstacles", m.ObstacleRequest(action="remove", id=oid))
        c.leg = None
        if legs is not None:
            legs.append(leg)
        if leg.obstacles:
            c.detours.append(leg.final_plan is not None)
    return result


async def run_scenario(sc: Scenario, session, keys: Keys, *, goal_timeout_s: float, plots: bool,  # noqa: ANN001
                       progress=print, truth_yaml: str | Path | None = None,  # noqa: ANN001
                       ) -> tuple[list[dict], list[Leg], int, list[bool], Any]:
    """Run the mapping phase (when the scenario has one; ``truth_yaml`` is the world's ground-truth map) and the
    goals; returns (runs, plotted legs, collisions, detours per obstacle leg, MappingResult or None)."""
    from services.common.robot import RobotSpec

    spec = RobotSpec()
    loop = asyncio.get_running_loop()
    c = Client(session, keys, loop)
    legs: list[Leg] = []
    runs = []
    mapping = None
    try:
        # the simulator builds a large map's world (2048x2048 cells: over a minute on a loaded machine) after its
        # health token is up
        deadline = time.monotonic() + 240
        while c.truth is None or c.sim_time <= 0:
            if time.monotonic() > deadline:
                raise RuntimeError("no sim/ground_truth within 240 s")
            await asyncio.sleep(0.05)
        if sc.mapping is not None:
            from services.cli.scenario_mapping import run_mapping
            from services.common.robot import RobotSpec

            if truth_yaml is None:
                raise RuntimeError("the mapping phase needs the ground-truth map")
            mp = sc.mapping
            mapping = await run_mapping(c, sc.start, mp.route, mp.save_as, mp.jog_speed_mps, truth_yaml, RobotSpec(),
                                        progress)
        for run in range(1, sc.repeats + 1):
            try:
                await place_robot(c, sc.start)
            except (RuntimeError, QueryError) as exc:  # report the runs done so far
                progress(f"scenario: stopped before run {run}: {exc}")
                c.aborted = True
                break
            goals = []
            for k, goal in enumerate(sc.goals, 1):
                res = await run_goal(c, sc, run, k, goal, goal_timeout_s, legs if plots and run == 1 else None,
                                     spec.goal_xy_tolerance_m, spec.goal_yaw_tolerance_rad)
                goals.append(res)
                err = ", ".join(f"{v:+.3f}" if v is not None else "-" for v in res["error"])
                loc = ", ".join(f"{v:+.3f}" for v in c.localization_errors[-1]) if c.localization_errors else "-"
                progress(f"scenario: run {run} goal {goal.id}: {'reached' if res['reached'] else 'NOT reached'}"
                         f" error {err} in {res['time_s']:.1f} s (localization estimate - truth: {loc})")
            runs.append({"run": run, "goals": goals})
    finally:
        c.close()
    if c.aborted:
        runs.append({"run": len(runs) + 1, "goals": [
            {"id": g.id, "target": list(g.pose), "reached": False, "final": [None] * 3, "error": [None] * 3,
             "time_s": 0.0} for g in sc.goals]})
    return runs, legs, c.collisions, c.detours, mapping


def draw_plots(legs: list[Leg], grid: m.OccupancyGrid | None, out_dir: Path) -> list[Path]:
    """Per leg: map + planned path + driven path as heading arrows; vx, vy, wz against time (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    files = []
    for k, leg in enumerate(legs, 1):
        tr = np.asarray(leg.trace, dtype=float).reshape(-1, 7)
        fig, ax = plt.subplots(figsize=(9, 6))
        if grid is not None and grid.width:
            data = codec.array(grid, "data").reshape(grid.height, grid.width)
            img = np.where(data < 0, 0.6, 1.0 - np.clip(data, 0, 100) / 100.0)
            ext = [grid.origin.x, grid.origin.x + grid.width * grid.resolution, grid.origin.y,
                   grid.origin.y + grid.height * grid.resolution]
            ax.imshow(img, cmap="gray", origin="lower", extent=ext, vmin=0, vmax=1)
        for r in leg.obstacles:
            ax.add_patch(plt.Rectangle((r[0], r[1]), r[2] - r[0], r[3] - r[1], color="orange", alpha=0.8,
                                       label="dynamic obstacle"))
        if leg.plan is not None and len(leg.plan):
            ax.plot(leg.plan[:, 0], leg.plan[:, 1], "b-", lw=1.5, label="global plan")
        if leg.final_plan is not None:
            ax.plot(leg.final_plan[:, 0], leg.final_plan[:, 1], "c--", lw=1.2, label="replanned around the obstacle")
        if len(tr):
            step = max(1, len(tr) // 60)
            s = tr[::step]
            ax.quiver(s[:, 1], s[:, 2], np.cos(s[:, 3]), np.sin(s[:, 3]), color="r", scale=40, width=0.003,
                      label="driven (heading)")
            pad = 2.0
            xs = np.concatenate([tr[:, 1], [leg.goal.pose[0]]])
            ys = np.concatenate([tr[:, 2], [leg.goal.pose[1]]])
            ax.set_xlim(xs.min() - pad, xs.max() + pad)
            ax.set_ylim(ys.min() - pad, ys.max() + pad)
        ax.plot(*leg.goal.pose[:2], "g*", ms=12, label=f"goal {leg.goal.id}")
        ax.set_aspect("equal")
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.legend(loc="best", fontsize=8)
        ax.set_title(f"run {leg.run}, leg {k}: to goal {leg.goal.id}")
        f = out_dir / f"leg{k:02d}_goal{leg.goal.id}_path.png"
        fig.savefig(f, dpi=110, bbox_inches="tight")
        plt.close(fig)
        files.append(f)
        if len(tr):
            fig, ax = plt.subplots(figsize=(9, 4))
            t = tr[:, 0] - tr[0, 0]
            ax.plot(t, tr[:, 4], label="vx (m/s)")
            ax.plot(t, tr[:, 5], label="vy (m/s)")
            ax.plot(t, tr[:, 6], label="wz (rad/s)")
            ax.set_xlabel("time (s)")
            ax.grid(True, alpha=0.3)
            ax.legend(loc="best", fontsize=8)
            ax.set_title(f"run {leg.run}, leg {k}: velocities to goal {leg.goal.id}")
            f = out_dir / f"leg{k:02d}_goal{leg.goal.id}_velocity.png"
            fig.savefig(f, dpi=110, bbox_inches="tight")
            plt.close(fig)
            files.append(f)
    return files


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("scenario", help="run navigation scenarios in the simulator")
    ssub = p.add_subparsers(dest="scenario_command", required=True, metavar="ACTION")
    rp = ssub.add_parser("run", help="run a scenario file and print the error table")
    rp.add_argument("file", help="scenario TOML")
    rp.add_argument("--json", help="write the per-run results to this file")
    rp.add_argument("--plots", help="write per-leg path and velocity plots (PNG) into this folder")
    rp.add_argument("--goal-timeout", type=float, default=900.0, help="sim seconds per goal (default %(default)s)")
    rp.add_argument("--repeats", type=int, help="override the file's repeats")
    rp.add_argument("--speed", type=float, help="override the file's sim speed factor")
    rp.add_argument("--set", action="append", default=[], metavar="SERVICE.KEY=VALUE",
                    help="config override passed to the stack (zagv up --set)")
    rp.add_argument("--run-dir", help="folder for the stack's run state and log (default: temporary)")
    rp.add_argument("--start-seed", type=int, help="start the stack's services in a random order (zagv up)")
    rp.add_argument("--start-delay-max", type=float, default=0.0, metavar="S",
                    help="with --start-seed: random 0..S s delay before each service (zagv up)")
    rp.set_defaults(func=run)
    from services.cli.scenario_generate import add_parser as add_generate

    add_generate(ssub)
    from services.cli.scenario_suite import add_parser as add_suite

    add_suite(ssub)


def run(args: argparse.Namespace) -> int:
    from services.cli.stack_process import Stack

    try:
        sc = load_scenario(args.file)
    except ScenarioError as exc:
        print(f"zagv scenario: {exc}", file=sys.stderr)
        return 2
    if args.repeats:
        sc.repeats = args.repeats
    if args.speed:
        sc.speed = args.speed
    if sc.robots:
        from services.cli.scenario_fleet import run_fleet

        return run_fleet(sc, args)
    run_dir = Path(args.run_dir or tempfile.mkdtemp(prefix="zagv-scenario-"))
    run_dir.mkdir(parents=True, exist_ok=True)
    extra = ["--headless"]
    if sc.mapping is not None:  # SLAM's map frame starts where the simulated robot starts: at the scenario's start
        x, y, th = sc.start
        extra += ["--mapping", "--set", f"sim.start_pose=[{x!r}, {y!r}, {th!r}]",
                  "--set", f"localization.initial_pose_x={x!r}", "--set", f"localization.initial_pose_y={y!r}",
                  "--set", f"localization.initial_pose_yaw={th!r}"]
    extra += [a for s in args.set for a in ("--set", s)]
    if args.start_seed is not None:
        extra += ["--start-seed", str(args.start_seed), "--start-delay-max", str(args.start_delay_max)]
    stack = Stack(run_dir, None, world=sc.world or "corridor", map_yaml=sc.map_yaml, speed=sc.speed,
                  extra_args=extra)
    print(f"zagv scenario: starting the simulated stack (log {run_dir / 'stack.log'})", flush=True)
    try:
        stack.start(ready_timeout_s=120.0)
        session = stack.session()

        truth_yaml = sc.map_yaml or str(run_dir / "world.yaml")  # zagv up renders the world there

        async def main() -> tuple[list[dict], list[Leg], int, list[bool], Any, m.OccupancyGrid | None]:
            runs, legs, collisions, detours, mapping = await run_scenario(
                sc, session, stack.keys, goal_timeout_s=args.goal_timeout, plots=bool(args.plots),
                progress=lambda s: print(s, flush=True), truth_yaml=truth_yaml)
            grid = None
            if args.plots:
                with contextlib.suppress(QueryError):
                    grid = await query(session, stack.keys, "map", m.Empty(), timeout_s=5.0)
            return runs, legs, collisions, detours, mapping, grid

        runs, legs, collisions, detours, mapping, grid = asyncio.run(main())
    except (AssertionError, RuntimeError, QueryError) as exc:
        print(f"zagv scenario: {exc}", file=sys.stderr)
        return 1
    finally:
        stack.stop()
    summary = summarize(runs)
    if mapping is not None:
        print(mapping.line())
    print(format_table(summary))
    total = sum(r["total"] for r in summary)
    reached = sum(r["reached"] for r in summary)
    tot = leg_totals(runs)
    print(f"reached {reached}/{total} goals within tolerance (ground truth); nav claimed {tot['claimed']}, "
          f"{tot['claimed_outside']} of them outside the tolerance; collisions: {collisions}; recoveries: "
          f"{tot['recoveries']}; localization error max {tot['loc_error_max_m']:.3f} m, RMS "
          f"{tot['loc_error_rms_m']:.3f} m; {tot['time_per_metre_s']:.1f} s per metre driven")
    if detours:
        print(f"replanned around the dynamic obstacle in {sum(detours)}/{len(detours)} legs")
    if args.json:
        result: dict[str, Any] = {"runs": runs}
        if mapping is not None:
            result["mapping"] = mapping.to_json()
        Path(args.json).write_text(json.dumps(result, indent=2))
    if args.plots:
        files = draw_plots(legs, grid, Path(args.plots))
        print(f"plots: {len(files)} files in {args.plots}")
    return 0 if reached == total and collisions == 0 else 1
