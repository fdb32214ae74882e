"""The ``zagv`` command: one entry point whose subcommands live in their own modules.

Each module in ``COMMANDS`` exposes ``register(subparsers)``, which adds its parser with ``func=`` set.
"""

from __future__ import annotations

import argparse
import importlib
import sys

COMMANDS = ["up", "router", "status", "topic", "bench", "map", "goal", "scenario", "install_units"]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="zagv", description="Zenoh-native control stack for a dual-swerve AGV")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMANDS:
        try:
            module = importlib.import_module(f"services.cli.{name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"services.cli.{name}":
                continue
            raise
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
