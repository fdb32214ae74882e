"""``zagv bench [--only PREFIX] [--json FILE]``: the arguments; running the groups is services.launch.bench."""

from __future__ import annotations

import argparse

from services.launch import bench


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="run benchmarks and print a table")
    p.add_argument("--only", help="run only groups/rows starting with this prefix (e.g. zenoh, amcl)")
    p.add_argument("--json", help="also write {\"rows\": [...]} to this file")
    p.add_argument("--list", action="store_true", help="list the groups and exit")
    p.set_defaults(func=bench.run)
