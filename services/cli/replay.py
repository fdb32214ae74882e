"""``zagv replay PATH [KEY ...]``: the arguments; playing a bag is services.recorder.replay."""

from __future__ import annotations

import argparse

from proto.keys import split_key
from services.cli.common import add_client_options, client_keys, client_settings


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("replay", help="play a zagv, ROS 2 (MCAP/sqlite3) or ROS 1 bag into the live services")
    add_client_options(p)
    p.add_argument("path", help="bag folder, split recording or ROS 1 .bag")
    p.add_argument("keys", nargs="*", metavar="KEY", help="topics to play (default: all the bag has)")
    p.add_argument("--rate", type=float, default=1.0, help="bag s per wall s (0: as fast as possible)")
    p.add_argument("--start", type=float, default=0.0, help="start S s after the bag's start")
    p.add_argument("--end", type=float, help="stop S s after the bag's start")
    p.add_argument("--loop", action="store_true", help="play again from --start when done")
    p.add_argument("--paused", action="store_true", help="start paused (space resumes, s steps)")
    p.add_argument("--remap", action="append", default=[], metavar="FROM:=TO", help="publish topic FROM as TO")
    p.add_argument("--no-clock", action="store_true", help="do not publish clock")
    p.add_argument("--clock-period", type=float, default=0.01, help="clock period in bag s (default %(default)s)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--no-service-requests", dest="service_requests", action="store_false",
                   help="do not issue the bag's recorded service requests again (default: issue them)")
    p.add_argument("--service-timeout", type=float, default=10.0,
                   help="wall s to wait for a service to take a re-issued request (default %(default)s)")
    p.set_defaults(func=run_replay)


def parse_remaps(items: list[str]) -> dict[str, str]:
    out = {}
    for item in items:
        src, sep, dst = item.partition(":=")
        if not sep or not src or not dst:
            raise SystemExit(f"zagv replay: --remap {item!r}: expected FROM:=TO")
        out[src.strip("/")] = dst.strip("/")
    return out

def run_replay(args: argparse.Namespace) -> int:
    from services.recorder.replay import ReplayOptions, replay

    wanted = {split_key(k)[1] if k.startswith("agv/") else k.strip("/") for k in args.keys} or None
    options = ReplayOptions(rate=args.rate, start_s=args.start, end_s=args.end, loop=args.loop, paused=args.paused,
                            publish_clock=not args.no_clock, clock_period_s=args.clock_period, quiet=args.quiet,
                            service_requests=args.service_requests, service_timeout_s=args.service_timeout)
    return replay(client_settings(args), client_keys(args), args.path, wanted, parse_remaps(args.remap), options)
