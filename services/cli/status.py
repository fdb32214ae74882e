"""``zagv status [--json]``: the arguments; collecting and printing is services.client.status."""

from __future__ import annotations

import argparse

from services.cli.common import add_client_options
from services.client import status


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("status", help="list the services and their health")
    add_client_options(p)
    p.add_argument("--json", action="store_true", help="print JSON")
    p.add_argument("--timeout", type=float, default=1.0, help="query timeout in s (default %(default)s)")
    p.set_defaults(func=status.run)
