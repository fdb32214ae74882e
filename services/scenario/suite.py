"""``zagv scenario suite [SUITE.toml] --maps-dir DIR``: the robustness benchmark over many maps.

For every map of the suite file and every seed, ``zagv scenario generate`` draws a scenario of reachable goals
(services/scenario/generate.py); one simulated stack per map then drives the goals of each seed in turn (the
robot teleported to that seed's start). Every goal is judged by the ground truth against the goal tolerance
(services/scenario/runner.py). The table has one row per map: goals, reached, what nav claimed and how often it
claimed success outside the tolerance, collisions, recoveries, max and RMS localization error, time per metre.

Suite TOML::

    goals = 5                 # per seed and map
    seeds = [1, 2, 3]
    speed = 4.0               # sim speed factor
    [[maps]]
    world = "warehouse"       # a built-in sim world, or
    [[maps]]
    map = "mit_stata_basement/stata_basement.yaml"   # a ROS map YAML, relative to --maps-dir (else the suite file)
    name = "mit_stata_basement"                      # optional row name
    cell_m = 0.10                                    # optional: re-rastered onto a coarser cell first

``cell_m`` re-rasters the map onto a coarser cell before the run: the whole multiple of the map's cell nearest to it
(``services.common.map_io.coarsen``: a block is occupied when any of its cells is, free when mostly free), written
into the run folder: the same building as a mapper with a coarser cell would have drawn it, for the sim world,
localization and nav alike.

A map whose YAML is missing is skipped (named in the output); a map on which no goal is reachable for the footprint
(too narrow for the robot) gets a row saying so and no goals.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import sys
import tempfile
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from services.scenario.generate import GenerateError, generate_file, map_label
from services.scenario.model import load_scenario
from services.scenario.report import leg_totals
from services.scenario.runner import run_scenario, unreached_goal_result


@dataclass
class SuiteMap:
    name: str
    world: str | None = None
    map_yaml: str | None = None
    #: re-raster the map onto this coarser cell (m) before the run
    cell_m: float | None = None


@dataclass
class Suite:
    maps: list[SuiteMap]
    goals: int = 5
    seeds: tuple[int, ...] = (1, 2, 3)
    speed: float = 4.0


def load_suite(path: Path, maps_dir: Path | None) -> tuple[Suite, list[str]]:
    """The suite and the names of the maps skipped because their YAML is missing."""
    data = tomllib.loads(path.read_text())
    maps, skipped = [], []
    for k, e in enumerate(data.get("maps", []), 1):
        if ("world" in e) == ("map" in e):
            raise ValueError(f"{path}: maps[{k}] needs exactly one of `world` or `map`")
        if "world" in e:
            maps.append(SuiteMap(str(e.get("name", e["world"])), world=str(e["world"])))
            continue
        rel = Path(e["map"])
        candidates = [rel] if rel.is_absolute() else [(maps_dir or path.parent) / rel, path.parent / rel]
        found = next((c for c in candidates if c.is_file()), None)
        name = str(e.get("name", map_label(str(rel))))
        if found is None:
            skipped.append(name)
            continue
        cell_m = e.get("cell_m")
        if cell_m is not None and not (isinstance(cell_m, int | float) and math.isfinite(cell_m) and cell_m > 0):
            raise ValueError(f"{path}: maps[{k}].cell_m must be a positive number of metres, got {cell_m!r}")
        maps.append(SuiteMap(name, map_yaml=str(found.resolve()),
                             cell_m=None if cell_m is None else float(cell_m)))
    return Suite(maps, int(data.get("goals", 5)), tuple(int(s) for s in data.get("seeds", [1, 2, 3])),
                 float(data.get("speed", 4.0))), skipped


def coarse_map(entry: SuiteMap, run_dir: Path) -> SuiteMap:
    """The entry itself, or with ``cell_m`` its map re-rastered onto the whole multiple of its cell nearest to
    ``cell_m`` and written into ``run_dir``."""
    if not (entry.map_yaml and entry.cell_m):
        return entry
    from services.common.map_io import coarsen, load_map, save_map

    fine = load_map(entry.map_yaml)
    factor = max(1, round(entry.cell_m / fine.resolution))
    coarse_yaml, _ = save_map(coarsen(fine, factor), run_dir / f"{entry.name}_map")
    return SuiteMap(entry.name, map_yaml=str(coarse_yaml))


def run_map(entry: SuiteMap, suite: Suite, run_dir: Path, goal_timeout_s: float, extra_set: list[str],
            max_leg_m: float = 20.0) -> dict:
    """Generate and drive every seed's goals on one map; the map's row with its runs."""
    from services.launch.stack_process import Stack

    row: dict = {"map": entry.name, "runs": [], "note": ""}
    entry = coarse_map(entry, run_dir)
    files = []
    for seed in suite.seeds:
        try:
            files.append(generate_file(run_dir / f"{entry.name}_s{seed}.toml", map_yaml=entry.map_yaml,
                                       world=entry.world, n_goals=suite.goals, seed=seed, speed=suite.speed,
                                       name=f"{entry.name}_s{seed}", max_leg_m=max_leg_m))
        except GenerateError as exc:
            row["note"] = f"no goals: {exc}"
            return row
    extra = ["--headless"] + [a for s in extra_set for a in ("--set", s)]
    (run_dir / entry.name).mkdir(parents=True, exist_ok=True)
    stack = Stack(run_dir / entry.name, None, world=entry.world or "corridor", map_yaml=entry.map_yaml,
                  speed=suite.speed, extra_args=extra)
    print(f"zagv scenario suite: {entry.name}: starting the stack (log {run_dir / entry.name / 'stack.log'})",
          flush=True)
    try:
        stack.start(ready_timeout_s=180.0)
        session = stack.session()
        for seed, f in zip(suite.seeds, files, strict=True):
            sc = load_scenario(f)

            def progress(s: str, seed: int = seed) -> None:
                print(f"{entry.name} s{seed}: {s}", flush=True)

            try:
                runs, _, collisions, _, _ = asyncio.run(run_scenario(sc, session, stack.keys,
                                                                     goal_timeout_s=goal_timeout_s, plots=False,
                                                                     progress=progress))
            except (AssertionError, RuntimeError) as exc:  # that seed stopped; its goals count as not reached
                row["note"] += f"seed {seed} stopped: {exc}; "
                runs = [{"run": 1, "goals": [
                    unreached_goal_result(g, "not run", str(exc)) for g in sc.goals]}]
            for r in runs:
                r["seed"] = seed
            row["runs"].extend(runs)
    except (AssertionError, RuntimeError) as exc:
        row["note"] += f"stopped: {exc}"
    finally:
        stack.stop()
    return row


def row_figures(row: dict) -> dict:
    return {"map": row["map"], **leg_totals(row["runs"]), "note": row["note"]}


def format_rows(rows: list[dict]) -> str:
    head = (f"{'map':<22} {'goals':>5} {'reached':>8} {'claimed':>8} {'claim!ok':>8} {'coll':>4} {'recov':>5} "
            f"{'loc max m':>9} {'loc rms m':>9} {'s/m':>6}  note")
    lines = [head, "-" * len(head)]
    for r in rows:
        lines.append(f"{r['map']:<22} {r['goals']:>5} {r['reached']:>8} {r['claimed']:>8} {r['claimed_outside']:>8} "
                     f"{r['collisions']:>4} {r['recoveries']:>5} {r['loc_error_max_m']:>9.3f} "
                     f"{r['loc_error_rms_m']:>9.3f} {r['time_per_metre_s']:>6.1f}  {r['note']}")
    return "\n".join(lines)


def bench_rows(rows: list[dict], runs: list[dict]) -> list[dict]:
    """The ``scenario.suite_*`` summary and ``nav.time_per_metre_s`` (reached legs: sim s per ground-truth m)."""
    t = leg_totals(runs)
    n = max(t["goals"], 1)
    return [
        {"name": "scenario.suite_maps", "value": float(sum(1 for r in rows if r["goals"])), "unit": "maps",
         "goal": ">= 8"},
        {"name": "scenario.suite_goals", "value": float(t["goals"]), "unit": "goals", "goal": ">= 120"},
        {"name": "scenario.suite_reached_pct", "value": 100.0 * t["reached"] / n, "unit": "%", "goal": ">= 97"},
        {"name": "scenario.suite_collisions", "value": float(t["collisions"]), "unit": "count", "goal": "0"},
        {"name": "scenario.suite_claimed_outside", "value": float(t["claimed_outside"]), "unit": "count",
         "goal": "0"},
        {"name": "scenario.suite_recoveries", "value": float(t["recoveries"]), "unit": "count", "goal": ""},
        {"name": "scenario.suite_loc_error_max_m", "value": t["loc_error_max_m"], "unit": "m", "goal": ""},
        {"name": "scenario.suite_loc_error_rms_m", "value": t["loc_error_rms_m"], "unit": "m", "goal": ""},
        {"name": "nav.time_per_metre_s", "value": t["time_per_metre_s"], "unit": "s/m", "goal": "-> 5 (0.2 m/s)"},
    ]


def run_suite(args: argparse.Namespace) -> int:
    try:
        suite, skipped = load_suite(Path(args.file), Path(args.maps_dir) if args.maps_dir else None)
    except (OSError, ValueError, tomllib.TOMLDecodeError) as exc:
        print(f"zagv scenario suite: {exc}", file=sys.stderr)
        return 2
    if args.seeds:
        suite.seeds = tuple(int(s) for s in args.seeds.split(","))
    if args.goals:
        suite.goals = args.goals
    if args.speed:
        suite.speed = args.speed
    if args.only:
        wanted = set(args.only.split(","))
        suite.maps = [e for e in suite.maps if e.name in wanted]
    for name in skipped:
        print(f"zagv scenario suite: {name}: map not found (give --maps-dir), skipped", flush=True)
    run_dir = Path(args.run_dir or tempfile.mkdtemp(prefix="zagv-suite-"))
    run_dir.mkdir(parents=True, exist_ok=True)
    rows: list[dict[str, Any]] = []
    all_runs: list[dict[str, Any]] = []
    raw: list[dict[str, Any]] = []

    def write_json() -> None:
        if args.json:
            Path(args.json).write_text(json.dumps({"rows": rows, "bench": bench_rows(rows, all_runs),
                                                   "maps": raw, "skipped": skipped}, indent=1, default=str))

    for entry in suite.maps:
        row = run_map(entry, suite, run_dir, args.goal_timeout, args.set, getattr(args, "max_leg", 20.0))
        raw.append(row)
        all_runs.extend(row["runs"])
        rows.append(row_figures(row))
        print(format_rows(rows[-1:]), flush=True)
        write_json()
    print(format_rows(rows))
    for b in bench_rows(rows, all_runs):
        v = b["value"]
        print(f"{b['name']:<34} {v if not math.isfinite(v) else round(v, 4):>10} {b['unit']:<6} {b['goal']}")
    write_json()
    t = leg_totals(all_runs)
    return 0 if t["goals"] and t["reached"] == t["goals"] and t["collisions"] == 0 else 1
