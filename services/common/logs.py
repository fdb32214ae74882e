"""Logging with the service name on every line."""

from __future__ import annotations

import contextlib
import logging
import os
import sys


def setup_logging(service: str, level: str | None = None, show_logger: bool = False) -> None:
    """Log to stderr as ``HH:MM:SS.mmm LEVEL service: message`` (level from ZAGV_LOG_LEVEL, default INFO);
    ``show_logger`` adds the logger's name (``service [zagv.nav]: message``: a container's services share stderr)."""
    handler = logging.StreamHandler(sys.stderr)
    who = f"{service} [%(name)s]" if show_logger else service
    handler.setFormatter(
        logging.Formatter(f"%(asctime)s.%(msecs)03d %(levelname)s {who}: %(message)s", datefmt="%H:%M:%S")
    )
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level or os.environ.get("ZAGV_LOG_LEVEL", "INFO"))


def print_line(line: str) -> None:
    """Print and flush; once stdout is gone (a closed pipe: the reader died) further lines are dropped, so that
    shutting down the stack never fails on a log line."""
    try:
        print(line, flush=True)
    except (BrokenPipeError, ValueError, OSError):
        with contextlib.suppress(OSError, ValueError):
            sys.stdout = open(os.devnull, "w")  # noqa: SIM115 - lives as long as the process
