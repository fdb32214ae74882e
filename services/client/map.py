"""``zagv map ...`` (its arguments: services/cli/map.py): work with maps in the ROS map_server format.

``zagv map info YAML [--json]`` prints a map's size, resolution, origin and its free/occupied/unknown cell counts.
``zagv map build|eval|bench|localize ...`` is offline SLAM, localization's own entry point: it runs
``python -m services.localization.slam COMMAND ARGS...`` as a subprocess (arguments passed through unchanged, its
output relayed, its exit code returned), so the CLI does not import the service.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import threading
from typing import IO

from services.common.map_io import MapError, load_map


def info(args: argparse.Namespace) -> int:
    try:
        grid = load_map(args.yaml)
    except MapError as exc:
        print(f"zagv map info: {exc}", file=sys.stderr)
        return 2
    counts = grid.counts()
    ox, oy, oyaw = grid.origin
    summary = {
        "yaml": args.yaml,
        "width": grid.width,
        "height": grid.height,
        "resolution_m": grid.resolution,
        "size_m": [grid.width * grid.resolution, grid.height * grid.resolution],
        "origin": [ox, oy, oyaw],
        "cells": counts,
    }
    if args.json:
        print(json.dumps(summary, indent=2))
        return 0
    print(f"map {args.yaml}")
    print(f"  size        {grid.width} x {grid.height} cells, {summary['size_m'][0]:.2f} x "
          f"{summary['size_m'][1]:.2f} m")
    print(f"  resolution  {grid.resolution:g} m/cell")
    print(f"  origin      x {ox:g} m, y {oy:g} m, yaw {oyaw:g} rad")
    print(f"  cells       free {counts['free']}, occupied {counts['occupied']}, unknown {counts['unknown']}"
          + (f", other {counts['other']}" if counts["other"] else ""))
    return 0


#: offline SLAM subcommands of ``python -m services.localization.slam`` (name, help)
SLAM_COMMANDS = [
    ("build", "build a map (YAML+PGM) and trajectory from a .clf or .bag log"),
    ("eval", "relative-pose error (Kümmerle 2009) against ground-truth relations"),
    ("bench", "build + evaluate a map from every log in a folder (table)"),
    ("localize", "AMCL on corrected logs' real scans against their reference map"),
]
SLAM_MODULE = "services.localization.slam"


def _relay(src: IO[str], stream_name: str) -> None:
    """Copy lines to ``sys.<stream_name>``, looked up per line (pytest's capsys swaps it)."""
    for line in src:
        out = getattr(sys, stream_name)
        out.write(line)
        out.flush()


def run_slam_command(args: argparse.Namespace) -> int:
    """``python -m services.localization.slam <command> <args>``; its output relayed, its exit code returned."""
    cmd = [sys.executable, "-m", SLAM_MODULE, args.map_command, *args.slam_args]
    with subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, bufsize=1) as proc:
        assert proc.stdout is not None and proc.stderr is not None
        relays = [threading.Thread(target=_relay, args=(proc.stderr, "stderr"), daemon=True)]
        relays[0].start()
        try:
            _relay(proc.stdout, "stdout")
            proc.wait()
        except KeyboardInterrupt:
            proc.terminate()
            proc.wait()
            raise
        finally:
            for relay in relays:
                relay.join(timeout=5.0)
    return proc.returncode
