"""The fleet view's HTTP + WebSocket API (Litestar, msgspec bodies) and its web page.

Login rules are the robot HMI's (``services.common.web``, ``services.common.auth``): every route under ``/api``
except ``POST /api/login`` needs ``Authorization: Bearer <token>`` (the WebSocket and ``map.png`` may pass
``?token=``); JSON bodies only, decoded strictly. Status codes: 401 without a valid token, 404 for a robot never
heard at the site, 409 when the robot refuses (its reason in ``detail``), 422 for a body that does not validate
(NaN/inf, out of range, too many poses), 429 while a client is locked out, 503 when the robot is not at the site or
does not answer.

- ``GET /api/fleet``: every robot (pose, footprint, path, nav state, drive, battery, faults, presence) and events;
- ``GET /api/map``, ``GET /api/map.png``: the site map (the robots' shared map);
- ``POST /api/robots/{id}/goal`` ``{x, y, theta}``, ``POST /api/robots/{id}/poses`` ``{poses: [{x, y, theta}]}``,
  ``POST /api/robots/{id}/cancel``, ``POST /api/robots/{id}/estop``: the robot's ``nav/goal``, ``nav/waypoints``,
  ``nav/cancel`` and ``drive/estop`` queries, the only ones a site may send (deploy/site.md);
- ``GET /api/ws``: the ``/api/fleet`` document at ``ws_rate_hz``, closed (1008) once the token is revoked.
"""

from __future__ import annotations

import asyncio
import base64
import logging
import math
import re
from pathlib import Path
from typing import Annotated, Any

import msgspec
from litestar import Litestar, MediaType, Request, Response, Router, get, post, websocket
from litestar.connection import WebSocket
from litestar.exceptions import (
    ClientException,
    HTTPException,
    ValidationException,
    WebSocketDisconnect,
)
from litestar.static_files import create_static_files_router
from litestar.status_codes import HTTP_200_OK

from services.common.auth import LoginThrottled
from services.common.web import (
    TOKEN_IN_QUERY,
    ActionReply,
    UndecodableBody,
    bearer_token,
    require_token,
    security_layer,
    session_routes,
    strict_body,
)
from services.fleet.backend import FleetBackend, RobotRejected, RobotUnavailable, UnknownRobot

STATIC_DIR = Path(__file__).parent / "static"
log = logging.getLogger("zagv.fleet")

Coord = Annotated[float, msgspec.Meta(ge=-1e6, le=1e6, description="map frame, m")]
Angle = Annotated[float, msgspec.Meta(ge=-1e3, le=1e3, description="rad")]
ROBOT_ID = re.compile(r"[A-Za-z0-9_.-]{1,64}")


class PoseIn(msgspec.Struct, forbid_unknown_fields=True):
    """A map-frame pose: x, y (m), theta (rad)."""

    x: Coord
    y: Coord
    theta: Angle = 0.0


class PosesIn(msgspec.Struct, forbid_unknown_fields=True):
    """A pose list, driven in order (the robot's ``nav/waypoints``)."""

    poses: Annotated[list[PoseIn], msgspec.Meta(min_length=1, max_length=10000)]


class GoalAccepted(msgspec.Struct):
    accepted: bool
    goal_id: str
    robot_id: str


login, logout = session_routes("Log in with the fleet view's password; returns a bearer token")


def _backend(request: Request | WebSocket) -> FleetBackend:
    return request.app.state.backend


def _robot_id(robot_id: str) -> str:
    """``robot_id`` when it is a valid key chunk (letters, digits, ``_.-``), else 422 naming it."""
    if not ROBOT_ID.fullmatch(robot_id):
        raise ValidationException(f"robot id {robot_id[:70]!r} is not a robot id (letters, digits, '_', '.', '-')")
    return robot_id


@get("/fleet", summary="Every robot at the site: pose, footprint, path, state, battery, faults, presence")
async def fleet(request: Request) -> dict:
    return _backend(request).snapshot()


@get("/map", summary="The site map's metadata and image (PNG, base64)")
async def map_json(request: Request) -> dict:
    b = _backend(request)
    meta = b.map_meta()
    png = b.map_png()
    if png is not None:
        meta["png_base64"] = base64.b64encode(png).decode()
    return meta


@get("/map.png", media_type="image/png", opt={TOKEN_IN_QUERY: True}, summary="The site map (north up)")
async def map_png(request: Request) -> Response[bytes]:
    png = _backend(request).map_png()
    if png is None:
        raise RobotUnavailable("no map yet: no robot has published one")
    return Response(png, media_type="image/png")


@post("/robots/{robot_id:str}/goal", status_code=HTTP_200_OK, summary="Send one robot to a map pose")
async def robot_goal(request: Request, robot_id: str, data: PoseIn) -> GoalAccepted:
    r = await _backend(request).goal(_robot_id(robot_id), data.x, data.y, data.theta)
    return GoalAccepted(accepted=True, goal_id=r.goal_id, robot_id=robot_id)


@post("/robots/{robot_id:str}/poses", status_code=HTTP_200_OK, summary="Send one robot along a pose list")
async def robot_poses(request: Request, robot_id: str, data: PosesIn) -> GoalAccepted:
    b = _backend(request)
    if len(data.poses) > b.config.max_poses:
        raise ValidationException(f"a pose list holds at most {b.config.max_poses} poses (fleet.max_poses), "
                                  f"got {len(data.poses)}")
    r = await b.poses(_robot_id(robot_id), [(p.x, p.y, p.theta) for p in data.poses])
    return GoalAccepted(accepted=True, goal_id=r.goal_id, robot_id=robot_id)


@post("/robots/{robot_id:str}/cancel", status_code=HTTP_200_OK, summary="Cancel the robot's goal or pose list")
async def robot_cancel(request: Request, robot_id: str) -> ActionReply:
    r = await _backend(request).cancel(_robot_id(robot_id))
    return ActionReply(ok=True, message=r.message or "canceled")


@post("/robots/{robot_id:str}/estop", status_code=HTTP_200_OK,
      summary="E-stop the robot (releasing it takes an operator at the robot's own HMI)")
async def robot_estop(request: Request, robot_id: str) -> ActionReply:
    r = await _backend(request).estop(_robot_id(robot_id))
    return ActionReply(ok=True, message=r.message or "e-stop")


@websocket("/ws", opt={TOKEN_IN_QUERY: True})
async def ws(socket: WebSocket) -> None:
    """Streams the ``/api/fleet`` document at ``ws_rate_hz`` (wall time); closes 1008 once the token is revoked."""
    b: FleetBackend = socket.app.state.backend
    token = bearer_token(socket, query_allowed=True)
    await socket.accept()
    period = 1.0 / b.config.ws_rate_hz
    try:
        while True:
            if not b.tokens.valid(token):
                await socket.close(code=1008, reason="logged out or token expired")
                return
            await socket.send_data(msgspec.json.encode({"type": "fleet", **b.snapshot()}).decode(), mode="text")
            await asyncio.sleep(period)
    except (WebSocketDisconnect, OSError, RuntimeError):
        return


def _error(status: int, detail: str, headers: dict[str, str] | None = None, extra: Any = None) -> Response[dict]:
    body: dict[str, Any] = {"status_code": status, "detail": detail}
    if extra:
        body["extra"] = extra
    if status == 401:
        headers = {**(headers or {}), "www-authenticate": 'Bearer realm="zagv-fleet"'}
    return Response(body, status_code=status, headers=headers)


def _on_client_error(_: Request, exc: ClientException) -> Response[dict]:
    status = 422 if exc.status_code == 400 and not isinstance(exc, UndecodableBody) else exc.status_code
    return _error(status, str(exc.detail), dict(exc.headers or {}), exc.extra)


def _on_http(_: Request, exc: HTTPException) -> Response[dict]:
    return _error(exc.status_code, str(exc.detail), dict(exc.headers or {}), exc.extra)


def _on_internal(request: Request, exc: Exception) -> Response[dict]:
    log.error("%s %s failed", request.method, request.url.path, exc_info=exc)
    return _error(500, f"internal error ({type(exc).__name__}); see the fleet log")


@get("/", include_in_schema=False)
async def index() -> Response[bytes]:
    return Response((STATIC_DIR / "index.html").read_bytes(), media_type=MediaType.HTML)


def create_asgi_app(backend: FleetBackend):
    """The Litestar app inside the security layer (Host allow-list, security headers)."""
    api = Router(path="/api", guards=[require_token], before_request=strict_body,
                 route_handlers=[logout, fleet, map_json, map_png, robot_goal, robot_poses, robot_cancel, robot_estop,
                                 ws])
    public = Router(path="/api", route_handlers=[login], before_request=strict_body)
    app = Litestar(
        route_handlers=[public, api, index,
                        create_static_files_router(path="/static", directories=[STATIC_DIR], include_in_schema=False)],
        exception_handlers={
            ValidationException: lambda _, exc: _error(422, str(exc.detail), extra=exc.extra),
            ClientException: _on_client_error,
            HTTPException: _on_http,
            Exception: _on_internal,
            LoginThrottled: lambda _, exc: _error(429, str(exc), {"retry-after": str(max(1, math.ceil(
                exc.retry_after_s)))}),
            UnknownRobot: lambda _, exc: _error(404, str(exc.args[0]) if exc.args else "unknown robot"),
            RobotRejected: lambda _, exc: _error(409, str(exc)),
            RobotUnavailable: lambda _, exc: _error(503, str(exc)),
        },
        openapi_config=None,
        debug=False,
        logging_config=None,
    )
    app.state.backend = backend
    return security_layer(backend.config.host_allow_list())(app)
