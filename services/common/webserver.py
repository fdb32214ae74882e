"""uvicorn on a service's own event loop, on a socket bound before the app exists (for the web HMIs)."""

from __future__ import annotations

import contextlib
import socket
from typing import Any

import uvicorn


class LoopServer(uvicorn.Server):
    """uvicorn on the service's own loop; signals stay with ``service_main`` (which sets ``ctx.stop``)."""

    @contextlib.contextmanager
    def capture_signals(self):
        yield


def listen_socket(host: str, port: int, service: str) -> socket.socket:
    """A bound, listening TCP socket; raises OSError naming the service and the address when it is taken."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((host, port))
    except OSError as exc:
        sock.close()
        raise OSError(f"{service} cannot listen on {host}:{port}: {exc.strerror or exc}") from None
    sock.listen(128)
    sock.set_inheritable(True)
    return sock


def server(app: Any, tls_certificate: str, tls_private_key: str) -> LoopServer:
    """A LoopServer for ``app``: no lifespan, no access log, HTTPS when a certificate is given."""
    return LoopServer(uvicorn.Config(app, lifespan="off", log_config=None, log_level="warning", access_log=False,
                                     ws="websockets-sansio", ws_ping_interval=None,
                                     ssl_certfile=tls_certificate or None, ssl_keyfile=tls_private_key or None))
