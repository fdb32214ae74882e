"""The ``zagv`` command: one entry point whose subcommands live in their own modules.

Each module in ``COMMANDS`` exposes ``register(subparsers)``, which adds its parser with ``func=`` set.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from types import ModuleType

from services.cli import (
    bench,
    blackbox,
    goal,
    install_units,
    map,
    record,
    replay,
    router,
    scenario,
    status,
    topic,
    up,
)

COMMANDS: list[ModuleType] = [up, router, status, topic, bench, map, goal, scenario, install_units, record, replay,
                              blackbox]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="zagv", description="Zenoh-native control stack for a dual-swerve AGV")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for module in COMMANDS:
        module.register(sub)
    return parser


def _interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt(f"signal {signum}")


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    # SIGTERM unwinds like Ctrl-C, so that a command's cleanup (stopping the stack it started) runs;
    # `zagv up` installs its own handlers on its event loop
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _interrupt)
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
