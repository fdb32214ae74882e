"""``zagv blackbox save|list``: the arguments; the save query and the listing are services.client.blackbox."""

from __future__ import annotations

import argparse

from services.cli.common import add_client_options
from services.client import blackbox


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("blackbox", help="save the black box now, or list saved black box bags")
    bsub = p.add_subparsers(dest="blackbox_command", required=True, metavar="ACTION")
    sp = bsub.add_parser("save", help="save the last minutes now (the recorder service of `zagv up`)")
    add_client_options(sp)
    sp.add_argument("reason", nargs="?", default="cli", help="reason, part of the bag name (default %(default)s)")
    sp.add_argument("--timeout", type=float, default=30.0, help="seconds to wait for the bag (default %(default)s)")
    sp.set_defaults(func=blackbox.run_save)
    lp = bsub.add_parser("list", help="saved black box bags in a folder (the run folder's blackbox/)")
    lp.add_argument("folder", help="black box folder")
    lp.set_defaults(func=blackbox.run_list)
