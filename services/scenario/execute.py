"""``zagv scenario run FILE``: load a scenario, start the simulated stack it needs, run it and report.

The single-robot form runs here (services.scenario.runner drives the goals); ``[[robots]]`` scenarios go to
services.scenario.fleet and ``[vda5050]`` ones to services.scenario.vda5050. The format is documented in
services.scenario.runner.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import sys
import tempfile
from pathlib import Path
from typing import Any

from proto import messages as m
from services.common.query import QueryError, query
from services.launch.stack_process import Stack
from services.scenario.client import Leg
from services.scenario.fleet import run_fleet
from services.scenario.model import ScenarioError, load_scenario
from services.scenario.report import draw_plots, format_table, leg_totals, summarize
from services.scenario.runner import run_scenario
from services.scenario.vda5050 import run_vda5050_fleet


def run_file(args: argparse.Namespace) -> int:
    """``zagv scenario run``: start a stack for the scenario file, run it, print the table; exit code 0 when every
    goal was reached without a collision. ``[[robots]]`` and ``[vda5050]`` scenarios go to their own runners."""
    try:
        sc = load_scenario(args.file, args.maps_dir)
    except ScenarioError as exc:
        print(f"zagv scenario: {exc}", file=sys.stderr)
        return 2
    if args.repeats:
        sc.repeats = args.repeats
    if args.speed:
        sc.speed = args.speed
    if sc.vda5050 is not None:
        return run_vda5050_fleet(sc, args)
    if sc.robots:
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
    if getattr(args, "no_compose", False):
        extra += ["--no-compose"]
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
