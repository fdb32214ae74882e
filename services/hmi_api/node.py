"""hmi_api's asyncio shell: the Zenoh backend, the jog and recorder loops, and uvicorn on the same loop."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
from typing import Any

import uvicorn

from services.common.service import ServiceContext
from services.hmi_api.app import create_asgi_app
from services.hmi_api.backend import Backend
from services.hmi_api.config import HmiApiConfig

log = logging.getLogger("zagv.hmi_api")


class _LoopServer(uvicorn.Server):
    """uvicorn on the service's own loop; signals stay with ``service_main`` (which sets ``ctx.stop``)."""

    @contextlib.contextmanager
    def capture_signals(self):  # uvicorn's contract
        yield


def listen_socket(host: str, port: int) -> socket.socket:
    """A bound, listening TCP socket; raises OSError naming the address when it is taken."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((host, port))
    except OSError as exc:
        sock.close()
        raise OSError(f"hmi_api cannot listen on {host}:{port}: {exc.strerror or exc}") from None
    sock.listen(128)
    sock.set_inheritable(True)
    return sock


async def run(ctx: ServiceContext) -> None:
    config: HmiApiConfig = ctx.config["hmi_api"]
    sock = listen_socket(config.host, config.port)  # first: connections queue in the backlog from now on
    backend = Backend(ctx.node, ctx.robot, config)
    app = create_asgi_app(backend)
    tls: dict[str, Any] = {"ssl_certfile": config.tls_certificate, "ssl_keyfile": config.tls_private_key} \
        if config.tls_certificate else {}
    server = _LoopServer(uvicorn.Config(app, lifespan="off", log_config=None, log_level="warning", access_log=False,
                                        ws="websockets-sansio", ws_ping_interval=None, **tls))
    tasks = [ctx.node.spawn(backend.jog_loop(ctx.stop)), ctx.node.spawn(backend.record_loop(ctx.stop)),
             ctx.node.spawn(server.serve(sockets=[sock]))]
    node = ctx.node
    node.spawn(node.ready_when(lambda: "HTTP API serving" if server.started else None, ctx.stop))
    log.info("HMI at %s://%s:%d/ (API /api, OpenAPI /api/schema/openapi.json)", "https" if tls else "http",
             config.host, config.port)
    try:
        await ctx.stop.wait()
    finally:
        server.should_exit = True
        with contextlib.suppress(Exception, asyncio.CancelledError):
            await asyncio.wait_for(tasks[2], 3.0)
        for t in tasks:
            t.cancel()
        backend.close()
        sock.close()
