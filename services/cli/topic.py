"""``zagv topic list|echo|hz``: the arguments; the work is services.client.topic."""

from __future__ import annotations

import argparse

from services.cli.common import add_client_options
from services.client import topic


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("topic", help="list, echo or measure the rate of topics")
    tsub = p.add_subparsers(dest="topic_command", required=True, metavar="ACTION")

    lp = tsub.add_parser("list", help="topics seen on the network within --window seconds")
    add_client_options(lp)
    lp.add_argument("--window", type=float, default=1.0, help="listening time in s (default %(default)s)")
    lp.add_argument("--all", action="store_true", help="also list registered topics that were not seen")
    lp.set_defaults(func=topic.run_list)

    ep = tsub.add_parser("echo", help="print messages of a topic (JSON with --json)")
    add_client_options(ep)
    ep.add_argument("key", help="topic name (scan) or key expression (agv/r1/scan, agv/r1/nav/**)")
    ep.add_argument("--count", type=int, default=0, help="stop after N messages (0: run until Ctrl-C)")
    ep.add_argument("--json", action="store_true", help="one JSON object per line")
    ep.add_argument("--timeout", type=float, default=0.0, help="give up after T s without a message (0: never)")
    ep.set_defaults(func=topic.run_echo)

    hp = tsub.add_parser("hz", help="print the publishing rate of a topic")
    add_client_options(hp)
    hp.add_argument("key", help="topic name or key expression")
    hp.add_argument("--window", type=float, default=2.0, help="averaging window in s (default %(default)s)")
    hp.add_argument("--count", type=int, default=0, help="stop after N reports (0: run until Ctrl-C)")
    hp.set_defaults(func=topic.run_hz)
