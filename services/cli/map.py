"""``zagv map ...``: work with maps in the ROS map_server format.

``zagv map info YAML [--json]`` prints a map's size, resolution, origin and its free/occupied/unknown cell counts.
Further subcommands register themselves in the same group (``SUBCOMMANDS``).
"""

from __future__ import annotations

import argparse
import json
import sys

from services.localization.map_io import MapError, load_map


def info(args: argparse.Namespace) -> int:
    try:
        grid = load_map(args.yaml)
    except MapError as exc:
        print(f"zagv map info: {exc}", file=sys.stderr)
        return 2
    counts = grid.counts()
    ox, oy, oyaw = grid.origin
    summary = {
        "yaml": args.yaml,
        "width": grid.width,
        "height": grid.height,
        "resolution_m": grid.resolution,
        "size_m": [grid.width * grid.resolution, grid.height * grid.resolution],
        "origin": [ox, oy, oyaw],
        "cells": counts,
    }
    if args.json:
        print(json.dumps(summary, indent=2))
        return 0
    print(f"map {args.yaml}")
    print(f"  size        {grid.width} x {grid.height} cells, {summary['size_m'][0]:.2f} x "
          f"{summary['size_m'][1]:.2f} m")
    print(f"  resolution  {grid.resolution:g} m/cell")
    print(f"  origin      x {ox:g} m, y {oy:g} m, yaw {oyaw:g} rad")
    print(f"  cells       free {counts['free']}, occupied {counts['occupied']}, unknown {counts['unknown']}"
          + (f", other {counts['other']}" if counts["other"] else ""))
    return 0


def add_info(group: argparse._SubParsersAction) -> None:
    p = group.add_parser("info", help="print a map's size, resolution, origin and cell counts")
    p.add_argument("yaml", help="map YAML file (ROS map_server format)")
    p.add_argument("--json", action="store_true", help="print JSON instead of text")
    p.set_defaults(func=info)


#: functions that add one subcommand to the ``map`` group
def add_build(group: argparse._SubParsersAction) -> None:
    from services.cli.map_tools import add_build_parser

    add_build_parser(group)


def add_eval(group: argparse._SubParsersAction) -> None:
    from services.cli.map_tools import add_eval_parser

    add_eval_parser(group)


def add_bench(group: argparse._SubParsersAction) -> None:
    from services.cli.map_bench import add_bench_parser

    add_bench_parser(group)


def add_localize(group: argparse._SubParsersAction) -> None:
    from services.cli.map_bench import add_localize_parser

    add_localize_parser(group)


SUBCOMMANDS = [add_info, add_build, add_eval, add_bench, add_localize]


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("map", help="inspect and convert maps (ROS map_server YAML + image)")
    group = p.add_subparsers(dest="map_command", required=True, metavar="SUBCOMMAND")
    for add in SUBCOMMANDS:
        add(group)
