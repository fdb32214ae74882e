"""The simulated CAN bus: a python-can-remote server on 127.0.0.1 over python-can's ``virtual`` interface.

Every client (the drive service, the emulated RoboteQ nodes, test-side masters) connects with
``can.Bus(interface="remote", channel="ws://127.0.0.1:<port>/")`` and sees every frame the others send.
Run: ``python -m services.sim.canbus --port 54701``.
"""

from __future__ import annotations

import argparse
import logging
import signal
import threading

from can_remote.server import RemoteServer

from services.common.lifetime import die_with_parent
from services.common.logs import setup_logging

DEFAULT_PORT = 54701


def main(argv: list[str] | None = None) -> None:
    die_with_parent()
    p = argparse.ArgumentParser(prog="python -m services.sim.canbus", description=__doc__.splitlines()[0])
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default %(default)s)")
    p.add_argument("--port", type=int, default=DEFAULT_PORT, help="TCP port (default %(default)s)")
    p.add_argument("--channel", default="zagv_sim", help="virtual bus channel name (default %(default)s)")
    args = p.parse_args(argv)
    setup_logging("canbus")
    logging.getLogger("can").setLevel(logging.WARNING)
    server = RemoteServer(args.host, args.port, bustype="virtual", channel=args.channel, receive_own_messages=False)
    thread = threading.Thread(target=server.serve_forever, name="canbus", daemon=True)
    thread.start()
    logging.getLogger("zagv.canbus").info("simulated CAN bus on ws://%s:%d/ (virtual channel %s)",
                                          args.host, args.port, args.channel)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    stop.wait()
    server.shutdown()
    server.server_close()


if __name__ == "__main__":
    main()
