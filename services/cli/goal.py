"""``zagv goal X Y THETA``: the arguments; sending and following the goal is services.client.goal."""

from __future__ import annotations

import argparse

from services.cli.common import add_client_options
from services.client import goal


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("goal", help="send a navigation goal and follow it")
    add_client_options(p)
    p.add_argument("x", type=float, help="goal x in the map frame (m)")
    p.add_argument("y", type=float, help="goal y in the map frame (m)")
    p.add_argument("theta", type=float, help="goal heading (rad)")
    p.add_argument("--id", default="", help="goal id (default: assigned by nav)")
    p.add_argument("--no-wait", action="store_true", help="return once the goal is accepted")
    p.add_argument("--timeout", type=float, default=0.0, help="cancel after T s of wall time (0: no limit)")
    p.add_argument("--accept-timeout", type=float, default=30.0, metavar="S",
                   help="wait up to S s for nav to take the goal (it answers once it has a map and a pose; "
                        "default %(default)s)")
    p.set_defaults(func=goal.run)
