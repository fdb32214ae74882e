"""A scenario file (TOML) as data: the world or map, start, repeats, speed, goals, dynamic obstacles and the optional
mapping phase; ``load_scenario`` checks it and names what is wrong (the format: services/scenario/runner.py)."""

from __future__ import annotations

import math
import os
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from proto import messages as m


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
    """The ``[mapping]`` table: the jog route, the saved map's name, the jog speed and how far the built map itself
    may lie from the world at a goal (added to the goal tolerance when goals are judged against the ground truth)."""

    route: list[tuple[float, float, float]]
    save_as: str
    jog_speed_mps: float
    map_error_allowance_m: float = 0.0


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
    #: several robots in one world, each with its own start and goals (services/scenario/fleet.py)
    robots: list[ScenarioRobot] = field(default_factory=list)
    #: the ``[vda5050]`` table: the robots' goals become VDA 5050 orders of a master control
    #: (services/scenario/vda5050.py)
    vda5050: Vda5050Orders | None = None


@dataclass
class Vda5050Orders:
    """``[vda5050]``: each robot's goals are the nodes of one order (after a first node at its start), assigned by
    the third-party master control to every robot at once (or one after another with ``sequential``)."""

    allowed_deviation_xy_m: float = 0.2
    allowed_deviation_theta_rad: float = 0.2
    sequential: bool = False


def _vda5050(raw: Any, p: Path) -> Vda5050Orders:
    if not isinstance(raw, dict):
        raise ScenarioError(f"{p}: vda5050 must be a table ([vda5050]), got {raw!r}")
    known = {"allowed_deviation_xy_m", "allowed_deviation_theta_rad", "sequential"}
    extra = sorted(set(raw) - known)
    if extra:
        raise ScenarioError(f"{p}: vda5050: unknown key(s) {', '.join(extra)}; known: {', '.join(sorted(known))}")
    out = Vda5050Orders()
    for name in ("allowed_deviation_xy_m", "allowed_deviation_theta_rad"):
        v = raw.get(name, getattr(out, name))
        if isinstance(v, bool) or not isinstance(v, int | float) or not 0 < v <= 10:
            raise ScenarioError(f"{p}: vda5050.{name} must be a number in (0, 10], got {v!r}")
        setattr(out, name, float(v))
    sequential = raw.get("sequential", False)
    if not isinstance(sequential, bool):
        raise ScenarioError(f"{p}: vda5050.sequential must be true or false, got {sequential!r}")
    out.sequential = sequential
    return out


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
    extra = sorted(set(raw) - {"route", "save_as", "jog_speed_mps", "map_error_allowance_m"})
    if extra:
        raise ScenarioError(f"{p}: mapping: unknown key(s) {', '.join(extra)}; known: jog_speed_mps, "
                            "map_error_allowance_m, route, save_as")
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
    allowance = raw.get("map_error_allowance_m", 0.0)
    if isinstance(allowance, bool) or not isinstance(allowance, int | float) or not 0 <= allowance <= 1.0:
        raise ScenarioError(f"{p}: mapping.map_error_allowance_m must be a number in [0, 1] (m), got {allowance!r}")
    return Mapping(route, save_as, float(speed), float(allowance))


def load_scenario(path: str | Path, maps_dir: str | Path | None = None) -> Scenario:
    """Read and check a scenario file. A relative ``map`` is looked up next to the file, then in ``maps_dir`` (the
    folder holding public map sets; default: the ``ZAGV_MAPS_DIR`` environment variable), then in the current
    folder."""
    p = Path(path)
    if maps_dir is None and os.environ.get("ZAGV_MAPS_DIR"):
        maps_dir = os.environ["ZAGV_MAPS_DIR"]
    try:
        data = tomllib.loads(p.read_text())
    except OSError as exc:
        raise ScenarioError(f"{p}: cannot read: {exc.strerror or exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ScenarioError(f"{p}: TOML syntax error: {exc}") from None
    known = {"world", "map", "start", "repeats", "speed", "goals", "dynamic_obstacles", "name", "description", "robots",
             "mapping", "vda5050"}
    unknown = sorted(set(data) - known)
    if unknown:
        raise ScenarioError(f"{p}: unknown key(s) {', '.join(unknown)}; known: {', '.join(sorted(known))}")
    if ("world" in data) == ("map" in data):
        raise ScenarioError(f"{p}: give exactly one of `world` (built-in name) or `map` (ROS map YAML)")
    map_yaml = None
    if "map" in data:
        mp = Path(data["map"])
        candidates = [mp] if mp.is_absolute() else [(p.parent / mp).resolve(), *(
            [(Path(maps_dir) / mp).resolve()] if maps_dir is not None else []), mp.resolve()]
        found = [c for c in candidates if c.is_file()]
        if not found:
            raise ScenarioError(f"{p}: map {data['map']} not found (relative to the scenario file, the maps folder"
                                f" (--maps-dir or ZAGV_MAPS_DIR) or the current folder: "
                                f"{', '.join(map(str, candidates))})")
        map_yaml = str(found[0])
    goals_raw = data.get("goals", [])
    robots = []
    if "robots" in data:
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
        x0, y0, x1, y1 = (float(v) for v in rect)
        obstacles.append(DynamicObstacle((x0, y0, x1, y1), during, float(o.get("appear_after_s", 0.0))))
    repeats = int(data.get("repeats", 1))
    speed = float(data.get("speed", 1.0))
    if repeats < 1 or not speed > 0:
        raise ScenarioError(f"{p}: repeats must be >= 1 and speed > 0")
    name = data.get("name", p.stem)
    if not isinstance(name, str) or not name:
        raise ScenarioError(f"{p}: name must be a non-empty string, got {name!r}")
    mapping = _mapping(data["mapping"], p, name) if "mapping" in data else None
    vda5050 = None
    if "vda5050" in data:
        if not robots:
            raise ScenarioError(f"{p}: [vda5050] orders need [[robots]] (each robot's goals are its order's nodes)")
        vda5050 = _vda5050(data["vda5050"], p)
    return Scenario(goals, data.get("world"), map_yaml, _pose(data.get("start", [0.0, 0.0, 0.0]), "start"), repeats,
                    speed, obstacles, name, mapping, robots, vda5050)


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


ROBOT_KEYS = {"id", "start", "goals", "start_after_s"}


@dataclass
class ScenarioRobot:
    """One robot of a fleet scenario: its id, start pose, goals (in order) and delay before its first goal."""

    id: str
    start: tuple[float, float, float]
    goals: list[Goal]
    start_after_s: float = 0.0


def load_robots(raw: Any, p: Path) -> list[ScenarioRobot]:
    """The ``[[robots]]`` array; ScenarioError naming the entry and key."""
    if not isinstance(raw, list) or not raw:
        raise ScenarioError(f"{p}: robots must be a non-empty array of tables ([[robots]])")
    robots = []
    for k, r in enumerate(raw, 1):
        if not isinstance(r, dict):
            raise ScenarioError(f"{p}: robots[{k}] must be a table")
        extra = sorted(set(r) - ROBOT_KEYS)
        if extra:
            raise ScenarioError(f"{p}: robots[{k}]: unknown key(s) {', '.join(extra)}; known: "
                                f"{', '.join(sorted(ROBOT_KEYS))}")
        rid = r.get("id")
        if not isinstance(rid, str) or not rid or any(c in rid for c in "/*$?#: "):
            raise ScenarioError(f"{p}: robots[{k}].id must be a robot id (no / * $ ? # : or spaces), got {rid!r}")
        if "start" not in r:
            raise ScenarioError(f"{p}: robots[{k}] ({rid}) has no start")
        goals = parse_goals(r.get("goals", []), p, f"robots[{k}].goals")
        if not goals:
            raise ScenarioError(f"{p}: robots[{k}] ({rid}) has no [[robots.goals]]")
        delay = r.get("start_after_s", 0.0)
        if isinstance(delay, bool) or not isinstance(delay, int | float) or not 0.0 <= delay < math.inf:
            raise ScenarioError(f"{p}: robots[{k}].start_after_s must be a number >= 0, got {delay!r}")
        robots.append(ScenarioRobot(rid, _pose(r["start"], f"robots[{k}].start"), goals, float(delay)))
    ids = [r.id for r in robots]
    if len(set(ids)) != len(ids):
        raise ScenarioError(f"{p}: robot ids must be distinct, got {', '.join(ids)}")
    return robots


# --------------------------------------------------------------------------- results
