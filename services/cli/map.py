"""``zagv map info|build|eval|bench|localize``: the arguments; the work is services.client.map (offline SLAM is
localization's own entry point, run as a subprocess: the CLI does not import the service)."""

from __future__ import annotations

import argparse

from services.client import map as map_command
from services.client.map import SLAM_COMMANDS, SLAM_MODULE


def add_info(group: argparse._SubParsersAction) -> None:
    p = group.add_parser("info", help="print a map's size, resolution, origin and cell counts")
    p.add_argument("yaml", help="map YAML file (ROS map_server format)")
    p.add_argument("--json", action="store_true", help="print JSON instead of text")
    p.set_defaults(func=map_command.info)


def add_slam_command(group: argparse._SubParsersAction, name: str, help_text: str) -> None:
    # no options of its own (prefix "+" matches none): every argument, --help included, goes to the SLAM module
    p = group.add_parser(name, help=f"{help_text} (python -m {SLAM_MODULE} {name} --help)", add_help=False,
                         prefix_chars="+")
    p.add_argument("slam_args", nargs="*", help=argparse.SUPPRESS)
    p.set_defaults(func=map_command.run_slam_command)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("map", help="inspect and convert maps (ROS map_server YAML + image)")
    group = p.add_subparsers(dest="map_command", required=True, metavar="SUBCOMMAND")
    add_info(group)
    for name, help_text in SLAM_COMMANDS:
        add_slam_command(group, name, help_text)
