"""hmi_api's asyncio shell: the Zenoh backend, the jog and recorder loops, and uvicorn on the same loop."""

from __future__ import annotations

import asyncio
import contextlib
import logging

from services.common import webserver
from services.common.service import ServiceContext
from services.hmi_api.app import create_asgi_app
from services.hmi_api.backend import Backend
from services.hmi_api.config import HmiApiConfig

log = logging.getLogger("zagv.hmi_api")


async def run(ctx: ServiceContext) -> None:
    config: HmiApiConfig = ctx.config["hmi_api"]
    # first: connections queue in the backlog from now on
    sock = webserver.listen_socket(config.host, config.port, "hmi_api")
    backend = Backend(ctx.node, ctx.robot, config)
    app = create_asgi_app(backend)
    server = webserver.server(app, config.tls_certificate, config.tls_private_key)
    tasks = [ctx.node.spawn(backend.jog_loop(ctx.stop)), ctx.node.spawn(backend.record_loop(ctx.stop)),
             ctx.node.spawn(server.serve(sockets=[sock]))]
    node = ctx.node
    node.spawn(node.ready_when(lambda: "HTTP API serving" if server.started else None, ctx.stop))
    scheme = "https" if config.tls_certificate else "http"
    log.info("HMI at %s://%s:%d/ (API /api, OpenAPI /api/schema/openapi.json)", scheme, config.host, config.port)
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
