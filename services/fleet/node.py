"""The fleet service's asyncio shell: the Zenoh backend and uvicorn on the same loop."""

from __future__ import annotations

import asyncio
import contextlib
import logging

from services.common.service import ServiceContext
from services.common.webserver import listen_socket, server
from services.fleet.app import create_asgi_app
from services.fleet.backend import FleetBackend
from services.fleet.config import FleetConfig

log = logging.getLogger("zagv.fleet")


async def run(ctx: ServiceContext) -> None:
    config: FleetConfig = ctx.config["fleet"]
    sock = listen_socket(config.host, config.port, "fleet")
    backend = FleetBackend(ctx.node, ctx.robot, config)
    http = server(create_asgi_app(backend), config.tls_certificate, config.tls_private_key)
    serving = ctx.node.spawn(http.serve(sockets=[sock]))
    ctx.node.spawn(ctx.node.ready_when(lambda: "HTTP API serving, robots' keys subscribed" if http.started else None,
                                       ctx.stop))
    log.info("fleet view at %s://%s:%d/", "https" if config.tls_certificate else "http", config.host, config.port)
    try:
        await ctx.stop.wait()
    finally:
        http.should_exit = True
        with contextlib.suppress(Exception, asyncio.CancelledError):
            await asyncio.wait_for(serving, 3.0)
        serving.cancel()
        backend.close()
        sock.close()
