"""Zenoh session factory: router, peer or client on explicit endpoints, multicast scouting off."""

from __future__ import annotations

import json
import os

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
    # extra json5 keys ([zenoh.options] table, then $ZAGV_ZENOH_OPTIONS as a JSON object for a whole stack)
    extra = dict(settings.options)
    extra.update(json.loads(os.environ.get("ZAGV_ZENOH_OPTIONS", "{}")))
    for key, value in extra.items():
        if key.startswith("scouting/multicast"):
            raise ValueError(f"zenoh option {key!r}: multicast scouting stays off (explicit endpoints only)")
        conf.insert_json5(key, json.dumps(value))
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
