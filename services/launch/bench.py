"""``zagv bench [--only PREFIX] [--json FILE]``: run the benchmark groups and print a table.

Groups come from the ``BENCHES`` lists of each service's ``services/<name>/bench.py``, of the whole-stack benches in
``services/launch/bench_*.py`` and ``services/scenario/bench.py``, of the SLAM log bench and of the recording bench
(see services.common.bench), imported when the command runs. This discovery is developer tooling, imported
inside ``discover``, never at module level (services/cli/bench.py holds the arguments).
"""

from __future__ import annotations

import argparse
import json
import sys
import traceback
from collections.abc import Callable
from pathlib import Path

from services.common.bench import BenchRow


def discover() -> list[tuple[str, Callable[[], list[BenchRow]]]]:
    """Every (group, function) pair, cheapest first as each module lists them."""
    from services.drive import bench as drive_bench
    from services.hmi_api import bench as hmi_api_bench
    from services.launch import bench_fleet, bench_record, bench_stack, bench_zenoh
    from services.lidar import bench as lidar_bench
    from services.localization import bench as localization_bench
    from services.localization.slam import bench_fr079 as bench_slam
    from services.nav import bench as nav_bench
    from services.scenario import bench as bench_scenario
    from services.sim import bench as sim_bench

    modules = [bench_record, bench_scenario, bench_slam, bench_stack, bench_zenoh, drive_bench, hmi_api_bench,
               lidar_bench, localization_bench, nav_bench, sim_bench, bench_fleet]
    return [group for module in modules for group in module.BENCHES]


def selected(group: str, only: str | None) -> bool:
    return only is None or group.startswith(only) or only.startswith(group)


def format_table(rows: list[BenchRow]) -> str:
    w = max([len(r.name) for r in rows] + [4])
    lines = [f"{'name':<{w}}  {'value':>12}  {'unit':<8}  goal", "-" * (w + 36)]
    for r in rows:
        lines.append(f"{r.name:<{w}}  {r.value:>12.4g}  {r.unit:<8}  {r.goal}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    groups = discover()
    if args.list:
        for g, _ in groups:
            print(g)
        return 0
    rows: list[BenchRow] = []
    failed = []
    for group, fn in groups:
        if not selected(group, args.only):
            continue
        print(f"bench: {group} ...", file=sys.stderr, flush=True)
        try:
            rows.extend(r for r in fn() if args.only is None or selected(r.name, args.only) or
                        selected(group, args.only))
        except Exception:
            failed.append(group)
            traceback.print_exc()
    if not rows and not failed:
        print(f"zagv bench: no benchmark matches {args.only!r}", file=sys.stderr)
        return 2
    print(format_table(rows))
    if args.json:
        Path(args.json).write_text(json.dumps(
            {"rows": [{"name": r.name, "value": r.value, "unit": r.unit, "goal": r.goal} for r in rows]}, indent=2))
    if failed:
        print(f"zagv bench: failed groups: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0
