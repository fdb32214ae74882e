"""``zagv blackbox save [REASON]`` and ``zagv blackbox list DIR``: the recorder service's black box."""

from __future__ import annotations

import argparse
import asyncio
import sys
from pathlib import Path

from proto.messages import BlackBoxSaveRequest
from services.client.connect import client_keys, client_session
from services.common.node import QueryError, query


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
