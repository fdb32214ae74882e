"""The client session of a command: ``--connect`` endpoints (default the local router) and ``--robot-id``."""

from __future__ import annotations

import argparse

import zenoh

from proto.keys import Keys
from services.common.session import open_session
from services.common.settings import ZenohSettings

DEFAULT_ROUTER = "tcp/127.0.0.1:7447"


def client_settings(args: argparse.Namespace) -> ZenohSettings:
    """A client of ``--connect`` (default the local router); multicast scouting is off in every session."""
    return ZenohSettings(mode="client", connect=args.connect or [DEFAULT_ROUTER])


def client_session(args: argparse.Namespace) -> zenoh.Session:
    return open_session(client_settings(args))


def client_keys(args: argparse.Namespace) -> Keys:
    return Keys(args.robot_id)
