"""Zenoh session factory: router, peer or client on explicit endpoints, multicast scouting off."""

from __future__ import annotations

import json

import zenoh

from services.common.settings import ZenohSettings


def zenoh_config(settings: ZenohSettings) -> zenoh.Config:
    """A zenoh.Config for ``settings``; scouting by UDP multicast is disabled in every mode."""
    conf = zenoh.Config.from_file(settings.config_file) if settings.config_file else zenoh.Config()
    conf.insert_json5("mode", json.dumps(settings.mode))
    conf.insert_json5("scouting/multicast/enabled", "false")
    if settings.connect and settings.mode != "router":
        conf.insert_json5("connect/endpoints", json.dumps(settings.connect))
    if settings.mode == "router":
        conf.insert_json5("connect/endpoints", json.dumps([e for e in settings.connect if e not in settings.listen]
                                                          if settings.listen else []))
    if settings.listen:
        conf.insert_json5("listen/endpoints", json.dumps(settings.listen))
    elif settings.mode != "client":
        # a peer/router listens only where told to; never on every interface by default
        conf.insert_json5("listen/endpoints", json.dumps([]))
    if settings.mode == "client":
        # keep retrying the router forever rather than failing at start when it is not up yet
        conf.insert_json5("connect/timeout_ms", "-1")
        conf.insert_json5("connect/exit_on_failure", "false")
    return conf


def open_session(settings: ZenohSettings) -> zenoh.Session:
    """Open a zenoh session for ``settings``."""
    return zenoh.open(zenoh_config(settings))


def router_settings(listen: list[str]) -> ZenohSettings:
    """Settings of the embedded router listening on ``listen`` (loopback by default)."""
    return ZenohSettings(mode="router", connect=[], listen=listen)
