"""``zagv blackbox save [REASON]`` and ``zagv blackbox list DIR``: the recorder service's black box."""

from __future__ import annotations

import argparse
import asyncio
import sys
from pathlib import Path

from proto.messages import BlackBoxSaveRequest
from services.cli.common import add_client_options, client_keys, client_session
from services.common.node import QueryError, query


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("blackbox", help="save the black box now, or list saved black box bags")
    bsub = p.add_subparsers(dest="blackbox_command", required=True, metavar="ACTION")
    sp = bsub.add_parser("save", help="save the last minutes now (the recorder service of `zagv up`)")
    add_client_options(sp)
    sp.add_argument("reason", nargs="?", default="cli", help="reason, part of the bag name (default %(default)s)")
    sp.add_argument("--timeout", type=float, default=30.0, help="seconds to wait for the bag (default %(default)s)")
    sp.set_defaults(func=run_save)
    lp = bsub.add_parser("list", help="saved black box bags in a folder (the run folder's blackbox/)")
    lp.add_argument("folder", help="black box folder")
    lp.set_defaults(func=run_list)


def run_save(args: argparse.Namespace) -> int:
    session = client_session(args)
    try:
        reply = asyncio.run(query(session, client_keys(args), "recorder/save",
                                  BlackBoxSaveRequest(reason=args.reason), timeout_s=args.timeout))
    except QueryError as exc:
        print(f"zagv blackbox: {exc}", file=sys.stderr)
        return 1
    finally:
        session.close()
    print(f"zagv blackbox: {'saved ' if reply.ok else ''}{reply.message}")
    return 0 if reply.ok else 1


def run_list(args: argparse.Namespace) -> int:
    from services.common.bagfiles import list_bags

    for entry in list_bags(Path(args.folder)):
        print(f"{entry.name}  {entry.size_bytes / 1e6:7.2f} MB  {entry.duration_s:6.1f} s  {entry.messages} msgs")
    return 0
