"""``zagv scenario generate MAP.yaml --goals N --seed S [--out FILE]``: a scenario of reachable goals on any map.

The map is read as the simulator reads it (occupied, unknown and in-between cells are solid, a yawed origin is
resampled; services.common.world), so the goals are judged against the world the robot will actually drive in.

Clearance: ``d`` = Euclidean distance (m) from a cell centre to the nearest solid cell centre (cells outside the
map are solid). A cell is *drivable* when ``d >= robot_radius_m + corridor_margin_m`` (default 0.63 + 0.15 m: the
chassis plus room for localization and control error); drivable cells that are 8-connected form the regions the
footprint can sweep. A goal is *reachable* when ``d >= robot_radius_m + goal_margin_m`` at the goal (the footprint
has room around it) and the goal lies in the drivable region of the start. Goals are drawn uniformly (seeded) from
those cells, inside the bounding box of the walls (solid cells next to free ones: a floor plan drawn as lines on
a free background has no wall around the outside), each at least ``min_leg_m`` and at most ``max_leg_m`` in a
straight line from the previous goal (the first from the start). Without ``--start`` the start is drawn the same
way from the largest drivable region. Headings are uniform in (-pi, pi].
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage

DEFAULT_ROBOT_RADIUS_M = 0.63
DEFAULT_CORRIDOR_MARGIN_M = 0.15
DEFAULT_GOAL_MARGIN_M = 0.25


class GenerateError(ValueError):
    """The map or the options cannot give the goals asked for; the message says why."""


@dataclass
class FreeSpace:
    """The world's clearance field and drivable regions (rows along +y from ``origin``)."""

    resolution_m: float
    origin_xy: tuple[float, float]
    clearance_m: np.ndarray  # (rows, cols) float
    region: np.ndarray  # (rows, cols) int: drivable region label, 0 not drivable
    box: tuple[int, int, int, int]  # rows r0..r1, cols c0..c1 (exclusive) of the occupied cells' bounding box

    def cell(self, x: float, y: float) -> tuple[int, int]:
        return (int(math.floor((y - self.origin_xy[1]) / self.resolution_m)),
                int(math.floor((x - self.origin_xy[0]) / self.resolution_m)))

    def centre(self, r: Any, c: Any) -> tuple[Any, Any]:
        """Centre (x_m, y_m) of cells (row r, column c): scalars or arrays."""
        return (self.origin_xy[0] + (c + 0.5) * self.resolution_m, self.origin_xy[1] + (r + 0.5) * self.resolution_m)

    def clearance_at(self, x: float, y: float) -> float:
        r, c = self.cell(x, y)
        h, w = self.clearance_m.shape
        return float(self.clearance_m[r, c]) if 0 <= r < h and 0 <= c < w else 0.0

    def region_at(self, x: float, y: float) -> int:
        r, c = self.cell(x, y)
        h, w = self.region.shape
        return int(self.region[r, c]) if 0 <= r < h and 0 <= c < w else 0


def free_space(solid: np.ndarray, resolution_m: float, origin_xy: tuple[float, float], drivable_m: float
               ) -> FreeSpace:
    """Clearance and drivable regions of a solid raster (module docstring)."""
    padded = np.ones((solid.shape[0] + 2, solid.shape[1] + 2), dtype=bool)
    padded[1:-1, 1:-1] = solid
    clearance = ndimage.distance_transform_edt(~padded)[1:-1, 1:-1] * resolution_m
    region, _ = ndimage.label(clearance >= drivable_m, structure=np.ones((3, 3), dtype=bool))
    # walls: solid cells with a free 4-neighbour (a floor plan's lines, a SLAM map's walls and its unknown rim)
    free = ~padded
    near_free = free[:-2, 1:-1] | free[2:, 1:-1] | free[1:-1, :-2] | free[1:-1, 2:]
    rows, cols = np.nonzero(solid & near_free)
    if len(rows):
        box = (int(rows.min()), int(rows.max()) + 1, int(cols.min()), int(cols.max()) + 1)
    else:
        box = (0, solid.shape[0], 0, solid.shape[1])
    return FreeSpace(resolution_m, origin_xy, clearance, region, box)


def generate_goals(space: FreeSpace, n_goals: int, seed: int, start: tuple[float, float, float] | None = None, *,
                   goal_clearance_m: float, min_leg_m: float = 3.0, max_leg_m: float = 20.0, min_spacing_m: float = 1.0,
                   avoid: list[tuple[float, ...]] | None = None, avoid_m: float = 0.0,
                   rng: np.random.Generator | None = None,
                   ) -> tuple[tuple[float, float, float], list[tuple[float, float, float]]]:
    """(start, goals) drawn as the module docstring says; a drawn start and the goals keep ``avoid_m`` from every
    point of ``avoid`` (other robots' starts and goals); GenerateError when the map cannot give them."""
    rng = rng or np.random.default_rng(seed)
    r0, r1, c0, c1 = space.box
    inside = np.zeros(space.region.shape, dtype=bool)
    inside[r0:r1, c0:c1] = True
    goal_ok = (space.clearance_m >= goal_clearance_m) & (space.region > 0) & inside
    if avoid:
        rr, cc = np.indices(space.region.shape)
        cx, cy = space.centre(rr, cc)
        for p in avoid:
            goal_ok &= np.hypot(cx - p[0], cy - p[1]) >= avoid_m
    if start is None:
        sizes = np.bincount(space.region[goal_ok].ravel())
        if len(sizes) <= 1:
            raise GenerateError(f"no cell has {goal_clearance_m:.2f} m of clearance in a region drivable for the "
                                "footprint")
        sizes[0] = 0
        rows, cols = np.nonzero(goal_ok & (space.region == int(np.argmax(sizes))))
        k = int(rng.integers(len(rows)))
        x, y = space.centre(int(rows[k]), int(cols[k]))
        start = (round(x, 2), round(y, 2), round(float(rng.uniform(-math.pi, math.pi)), 2))
    label = space.region_at(start[0], start[1])
    if label == 0:
        raise GenerateError(f"start ({start[0]:.2f}, {start[1]:.2f}) is not in free space wide enough for the "
                            f"footprint (clearance {space.clearance_at(start[0], start[1]):.2f} m)")
    rows, cols = np.nonzero(goal_ok & (space.region == label))
    if len(rows) == 0:
        raise GenerateError(f"no cell with {goal_clearance_m:.2f} m of clearance is connected to the start"
                            + (f" and {avoid_m:.2f} m from the other robots' starts and goals" if avoid else ""))
    xs, ys = space.centre(rows, cols)
    goals: list[tuple[float, float, float]] = []
    previous = start
    for k in range(n_goals):
        d_prev = np.hypot(xs - previous[0], ys - previous[1])
        ok = (d_prev >= min_leg_m) & (d_prev <= max_leg_m)
        for g in goals:
            ok &= np.hypot(xs - g[0], ys - g[1]) >= min_spacing_m
        if not ok.any():  # a small map: take the farthest cells within reach instead
            ok = d_prev >= min(float(d_prev.max()), max_leg_m) * 0.5
        idx = np.flatnonzero(ok)
        j = int(idx[rng.integers(len(idx))])
        goal = (round(float(xs[j]), 2), round(float(ys[j]), 2), round(float(rng.uniform(-math.pi, math.pi)), 2))
        if space.clearance_at(goal[0], goal[1]) < goal_clearance_m - space.resolution_m:
            raise GenerateError(f"goal {k + 1} lost its clearance when rounded")  # cannot happen at 1 cm rounding
        goals.append(goal)
        previous = goal
    return start, goals


def scenario_toml(name: str, source: str, start: tuple[float, float, float], goals: list[tuple[float, float, float]],
                  speed: float, description: str) -> str:
    """The scenario file (services/scenario/runner.py format); ``source`` is a ``map = ...`` or ``world = ...`` line."""
    lines = [f"# {description}", f'name = "{name}"', source, f"start = [{start[0]}, {start[1]}, {start[2]}]",
             "repeats = 1", f"speed = {speed:g}", ""]
    for k, g in enumerate(goals, 1):
        lines += ["[[goals]]", f'id = "{k}"', f"pose = [{g[0]}, {g[1]}, {g[2]}]"]
    return "\n".join(lines) + "\n"


def generate_fleet(space: FreeSpace, n_robots: int, n_goals: int, seed: int,
                   start: tuple[float, float, float] | None = None, *, robot_radius_m: float, goal_clearance_m: float,
                   min_leg_m: float = 3.0, max_leg_m: float = 20.0, spacing_m: float = 0.6,
                   ) -> list[tuple[tuple[float, float, float], list[tuple[float, float, float]]]]:
    """(start, goals) per robot: robot 1 as ``generate_goals`` draws them; every further robot's start and goals
    keep ``2 * robot_radius_m + spacing_m`` from every start and goal of the robots before it (two robots never
    share a parking place), in the same drivable region as robot 1's start."""
    rng = np.random.default_rng(seed)
    separation = 2.0 * robot_radius_m + spacing_m
    out: list[tuple[tuple[float, float, float], list[tuple[float, float, float]]]] = []
    taken: list[tuple[float, ...]] = []
    for k in range(n_robots):
        s, goals = generate_goals(space, n_goals, seed, start if k == 0 else None, goal_clearance_m=goal_clearance_m,
                                  min_leg_m=min_leg_m, max_leg_m=max_leg_m, avoid=taken, avoid_m=separation, rng=rng)
        if k and space.region_at(s[0], s[1]) != space.region_at(out[0][0][0], out[0][0][1]):
            raise GenerateError(f"robot {k + 1}'s start is not connected to robot 1's")
        out.append((s, goals))
        taken += [s, *goals]
    return out


def fleet_scenario_toml(name: str, source: str, robots: list[tuple[tuple[float, float, float],
                                                                    list[tuple[float, float, float]]]],
                        speed: float, description: str) -> str:
    """A ``[[robots]]`` scenario (services/scenario/fleet.py): ids r1, r2, ..."""
    lines = [f"# {description}", f'name = "{name}"', source, f"speed = {speed:g}", ""]
    for k, (start, goals) in enumerate(robots, 1):
        lines += ["[[robots]]", f'id = "r{k}"', f"start = [{start[0]}, {start[1]}, {start[2]}]"]
        for j, g in enumerate(goals, 1):
            lines += ["[[robots.goals]]", f'id = "{j}"', f"pose = [{g[0]}, {g[1]}, {g[2]}]"]
        lines.append("")
    return "\n".join(lines)


def map_label(map_yaml: str) -> str:
    """A short name for a map: the YAML's stem, or its folder's name when the stem says nothing ("map")."""
    p = Path(map_yaml)
    return p.parent.name if p.stem in ("map", "") else p.stem


def load_solid(map_yaml: str | None, world: str | None):
    """The simulator's world for a map YAML or a built-in world name."""
    from services.common.world import load_world

    return load_world(world or "", map_yaml or "")


def generate_file(out: Path, *, map_yaml: str | None = None, world: str | None = None, n_goals: int, seed: int,
                  start: tuple[float, float, float] | None = None, robot_radius_m: float = DEFAULT_ROBOT_RADIUS_M,
                  corridor_margin_m: float = DEFAULT_CORRIDOR_MARGIN_M, goal_margin_m: float = DEFAULT_GOAL_MARGIN_M,
                  min_leg_m: float = 3.0, max_leg_m: float = 20.0, speed: float = 4.0, name: str = "",
                  robots: int = 1) -> Path:
    """Write a generated scenario to ``out`` (``robots`` > 1: a ``[[robots]]`` scenario); returns it."""
    w = load_solid(map_yaml, world)
    if start is None and world and not map_yaml:
        start = w.start_pose
    space = free_space(w.solid, w.resolution_m, w.origin_xy, robot_radius_m + corridor_margin_m)
    fleet = None
    if robots > 1:
        fleet = generate_fleet(space, robots, n_goals, seed, start, robot_radius_m=robot_radius_m,
                               goal_clearance_m=robot_radius_m + goal_margin_m, min_leg_m=min_leg_m,
                               max_leg_m=max_leg_m)
    else:
        start_pose, goals = generate_goals(space, n_goals, seed, start,
                                           goal_clearance_m=robot_radius_m + goal_margin_m, min_leg_m=min_leg_m,
                                           max_leg_m=max_leg_m)
    out.parent.mkdir(parents=True, exist_ok=True)
    if map_yaml:
        mp = Path(map_yaml).resolve()
        try:
            ref = mp.relative_to(out.parent.resolve())
        except ValueError:
            ref = mp
        source = f'map = "{ref}"'
    else:
        source = f'world = "{world}"'
    label = name or f"{map_label(map_yaml) if map_yaml else world}_s{seed}"
    desc = (f"generated: {n_goals} goals, seed {seed}, clearance >= {robot_radius_m + goal_margin_m:.2f} m at the"
            f" goals, connected to the start through space >= {robot_radius_m + corridor_margin_m:.2f} m from walls")
    if fleet is not None:
        desc = desc.replace("generated: ", f"generated: {robots} robots, ") + \
            f"; every start and goal {2 * robot_radius_m + 0.6:.2f} m from the other robots'"
        out.write_text(fleet_scenario_toml(label, source, fleet, speed, desc))
    else:
        out.write_text(scenario_toml(label, source, start_pose, goals, speed, desc))
    return out


def run_generate(args: argparse.Namespace) -> int:
    from services.common.world import WorldError

    if bool(args.map) == bool(args.world):
        print("zagv scenario generate: give a map YAML or --world NAME (one of them)", file=sys.stderr)
        return 2
    if args.goals < 1 or args.robots < 1:
        print("zagv scenario generate: --goals and --robots must be >= 1", file=sys.stderr)
        return 2
    start: tuple[float, float, float] | None = None
    if args.start:
        try:
            x, y, theta = (float(v) for v in args.start.split(","))
            if not all(math.isfinite(v) for v in (x, y, theta)):
                raise ValueError
            start = (x, y, theta)
        except ValueError:
            print(f"zagv scenario generate: --start must be x,y,theta numbers, got {args.start!r}", file=sys.stderr)
            return 2
    stem = map_label(args.map) if args.map else args.world
    out = Path(args.out or f"{stem}_s{args.seed}.toml")
    try:
        generate_file(out, map_yaml=args.map, world=args.world, n_goals=args.goals, seed=args.seed, start=start,
                      robot_radius_m=args.robot_radius, corridor_margin_m=args.corridor_margin,
                      goal_margin_m=args.goal_margin, min_leg_m=args.min_leg, max_leg_m=args.max_leg,
                      speed=args.speed, robots=args.robots)
    except (GenerateError, WorldError) as exc:
        print(f"zagv scenario generate: {exc}", file=sys.stderr)
        return 1
    print(f"zagv scenario generate: wrote {out}")
    return 0
