"""Options shared by the client-side subcommands (status, topic, goal, ...)."""

from __future__ import annotations

import argparse

from proto.keys import DEFAULT_ROBOT_ID, Keys
from services.common.session import open_session
from services.common.settings import ZenohSettings

DEFAULT_ROUTER = "tcp/127.0.0.1:7447"


def add_client_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--connect", action="append", help=f"router endpoint (default {DEFAULT_ROUTER})")
    p.add_argument("--robot-id", default=DEFAULT_ROBOT_ID, help="robot id (default %(default)s)")


def client_settings(args: argparse.Namespace) -> ZenohSettings:
    """A client of ``--connect`` (default the local router); multicast scouting is off in every session."""
    return ZenohSettings(mode="client", connect=args.connect or [DEFAULT_ROUTER])


def client_session(args: argparse.Namespace):  # zenoh.Session
    return open_session(client_settings(args))


def client_keys(args: argparse.Namespace) -> Keys:
    return Keys(args.robot_id)
