"""Offline SLAM from laser logs: ``python -m services.localization.slam build|eval|bench|localize ...``.

``build`` runs graph SLAM over a log and writes a map and trajectory, ``eval`` scores a trajectory against
ground-truth relations (services.localization.slam.map_tools); ``bench`` builds and scores every log of a folder
and ``localize`` runs AMCL on corrected logs against their reference maps (services.localization.slam.map_bench).
``zagv map build|eval|bench|localize`` runs this module as a subprocess with the same arguments.
"""

from __future__ import annotations

import argparse
import sys

from services.localization.slam.map_bench import add_bench_parser, add_localize_parser
from services.localization.slam.map_tools import add_build_parser, add_eval_parser

#: the subcommands, also offered by ``zagv map``
COMMANDS = ("build", "eval", "bench", "localize")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m services.localization.slam", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    add_build_parser(sub)
    add_eval_parser(sub)
    add_bench_parser(sub)
    add_localize_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
