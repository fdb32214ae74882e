"""``zagv router``: a standalone Zenoh router (a zenoh session in router mode) for hosts without zenohd."""

from __future__ import annotations

import argparse
import json
import signal
import threading

from services.common.lifetime import die_with_parent
from services.common.logs import setup_logging
from services.common.session import router_settings, zenoh_config
from services.common.settings import ZenohSettings

DEFAULT_LISTEN = "tcp/127.0.0.1:7447"


def config_listen_endpoints(path: str | None) -> list[str]:
    """The ``listen/endpoints`` list of a zenoh json5 file ([] when absent or when it is zenoh's per-mode default)."""
    if not path:
        return []
    import zenoh

    endpoints = json.loads(zenoh.Config.from_file(path).get_json("listen/endpoints"))
    return [str(e) for e in endpoints] if isinstance(endpoints, list) else []


def run(args: argparse.Namespace) -> int:
    import zenoh

    die_with_parent()
    setup_logging("router")
    settings = router_settings(args.listen or config_listen_endpoints(args.config) or [DEFAULT_LISTEN])
    if args.config or args.connect:
        settings = ZenohSettings(mode="router", connect=list(args.connect), listen=settings.listen,
                                 config_file=args.config or "")
    conf = zenoh_config(settings)
    dialled = json.loads(conf.get_json("connect/endpoints")) or []
    session = zenoh.open(conf)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    print(f"zagv router: listening on {', '.join(settings.listen)}"
          + (f"; linking to {', '.join(map(str, dialled))}" if dialled else ""), flush=True)
    try:
        from services.common import systemd

        systemd.notify("READY=1")
        period = systemd.watchdog_period_s()
        while not stop.wait(period or 3600):
            if period:
                systemd.notify("WATCHDOG=1")
    finally:
        session.close()
    return 0
