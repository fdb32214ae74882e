"""Options shared by the client-side subcommands (status, topic, goal, ...)."""

from __future__ import annotations

import argparse

from proto.keys import DEFAULT_ROBOT_ID
from services.client.connect import DEFAULT_ROUTER, client_keys, client_settings

__all__ = ["add_client_options", "client_keys", "client_settings"]


def add_client_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--connect", action="append", help=f"router endpoint (default {DEFAULT_ROUTER})")
    p.add_argument("--robot-id", default=DEFAULT_ROBOT_ID, help="robot id (default %(default)s)")
