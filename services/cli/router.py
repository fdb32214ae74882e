"""``zagv router``: the arguments; the router itself is services.launch.router."""

from __future__ import annotations

import argparse

from services.launch import router


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("router", help="run a Zenoh router (loopback by default; multicast scouting off)")
    p.add_argument("--listen", action="append",
                   help="endpoint to listen on (default: the config file's listen/endpoints, else "
                        f"{router.DEFAULT_LISTEN})")
    p.add_argument("--config", help="zenoh json5 config file applied first (TLS, access control)")
    p.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                   help="another router to link to, e.g. a robot's router to its site router "
                        "(default: the config file's connect/endpoints); retried while it is away")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    return router.run(args)
