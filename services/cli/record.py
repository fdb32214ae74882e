"""``zagv record [-o DIR] [KEY ...]``: the arguments; recording is services.recorder.record."""

from __future__ import annotations

import argparse

from proto.keys import split_key
from proto.registry import TOPICS
from services.cli.common import add_client_options, client_keys, client_settings


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("record", help="record topics to a rosbag2/MCAP bag (ROS 2 tools, Foxglove open it)")
    add_client_options(p)
    p.add_argument("keys", nargs="*", metavar="KEY", help="topic names or key expressions (default: every topic)")
    p.add_argument("-o", "--output", help="bag folder to create (default: zagv_<date>_<time>)")
    p.add_argument("--split-size-mb", type=float, default=0.0, help="start a new bag past this many MB (0: never)")
    p.add_argument("--split-duration", type=float, default=0.0, help="start a new bag every S s of log time (0: never)")
    p.add_argument("--duration", type=float, default=0.0, help="stop after S s of log time (0: until Ctrl-C)")
    p.add_argument("--quiet", action="store_true", help="no progress line")
    p.set_defaults(func=run_record)


def selected_names(keys: list[str]) -> list[str] | None:
    """Topic names to record from the KEY arguments (None: every registered topic)."""
    if not keys:
        return None
    names = []
    for k in keys:
        name = split_key(k)[1] if k.startswith("agv/") else k
        if name not in TOPICS:
            raise SystemExit(f"zagv record: unknown topic {k!r}; known: {', '.join(sorted(TOPICS))}")
        names.append(name)
    return names


def run_record(args: argparse.Namespace) -> int:
    from services.recorder.record import record

    names = selected_names(args.keys)
    return record(client_settings(args), client_keys(args), args.output, names, split_size_mb=args.split_size_mb,
                  split_duration_s=args.split_duration, duration_s=args.duration, quiet=args.quiet)
