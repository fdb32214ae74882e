"""The HTTP + WebSocket API (Litestar, msgspec bodies) and the static web HMI.

Every route under ``/api`` except ``POST /api/login`` needs ``Authorization: Bearer <token>``; only the WebSocket
and the GET downloads (``map.png``, ``velocities.csv``, ``poses/export``) may pass ``?token=`` instead, as browsers
cannot set headers there. Status codes: 401 without a valid token, 400 for a body that is not UTF-8, 415 for a body
that is not ``application/json``, 422 for a body or query parameter that does not validate (wrong type, NaN/inf,
out of range, missing field; the body names the field), 404 for an unknown pose, 409 when the robot refuses (its
reason in ``detail``) or the pose list is full, 429 while a client is locked out after wrong passwords (with
``Retry-After``), 503 when a robot service does not answer. JSON never contains NaN: non-finite numbers are sent as
null. A WebSocket is closed (code 1008) once its token is revoked (logout) or expires.

Every response carries a Content-Security-Policy (same origin only), ``X-Frame-Options: DENY``,
``X-Content-Type-Options: nosniff`` and ``Referrer-Policy: no-referrer``; a request whose ``Host`` is not in
``hmi_api.allowed_hosts`` gets 400 (DNS rebinding). The OpenAPI document is at ``/api/schema/openapi.json``, behind
login; no documentation page (those load scripts from a CDN) is served.
"""

from __future__ import annotations

import asyncio
import base64
import logging
import math
import sqlite3
import uuid
from pathlib import Path
from typing import Annotated, Any, Literal

import msgspec
from litestar import Litestar, MediaType, Request, Response, Router, delete, get, patch, post, websocket
from litestar.connection import WebSocket
from litestar.exceptions import (
    ClientException,
    HTTPException,
    ValidationException,
    WebSocketDisconnect,
)
from litestar.openapi import OpenAPIConfig
from litestar.openapi.plugins import JsonRenderPlugin
from litestar.openapi.spec import Components, SecurityScheme
from litestar.static_files import create_static_files_router
from litestar.status_codes import HTTP_200_OK

from services.common.auth import LoginThrottled
from services.common.web import (  # noqa: F401 - SECURITY_HEADERS is part of this module's interface
    SECURITY_HEADERS,
    TOKEN_IN_QUERY,
    ActionReply,
    LoginReply,
    LoginRequest,
    UndecodableBody,
    bearer_token,
    require_token,
    security_layer,
    session_routes,
    strict_body,
)
from services.hmi_api import blackbox
from services.hmi_api.backend import Backend, RobotRejected, RobotUnavailable
from services.hmi_api.posedb import NAME_MAX, PoseDbError, PoseListFull, PoseNotFound, PoseRecord

STATIC_DIR = Path(__file__).parent / "static"
log = logging.getLogger("zagv.hmi_api")

# Bounds keep every number finite (NaN and inf fail them -> 422); jog values are then clamped to Table 2.
Speed = Annotated[float, msgspec.Meta(ge=-1e3, le=1e3, description="m/s or rad/s; clamped to the robot's limits")]
Coord = Annotated[float, msgspec.Meta(ge=-1e6, le=1e6, description="map frame, m")]
Angle = Annotated[float, msgspec.Meta(ge=-1e3, le=1e3, description="rad, wrapped to (-pi, pi]")]
Name = Annotated[str, msgspec.Meta(min_length=1, max_length=NAME_MAX)]


# (?!\n) before $: a Python `$` also matches before a trailing newline ("m1\n" would pass)
MAP_NAME_PATTERN = r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}(?!\n)$"
MapName = Annotated[str, msgspec.Meta(pattern=MAP_NAME_PATTERN,
                                      description="a map name: letters, digits, '_', '-', '.'; no path")]


class MapSaveIn(msgspec.Struct, forbid_unknown_fields=True):
    """Save the map being built as ``<name>.yaml`` + ``<name>.pgm`` in the robot's maps folder."""

    name: MapName


class MapStopIn(msgspec.Struct, forbid_unknown_fields=True):
    """Stop mapping and navigate on ``map`` (the name of a map in the robot's maps folder, never a path; empty: the
    map saved last)."""

    map: Annotated[str, msgspec.Meta(pattern=r"^(?:[A-Za-z0-9_][A-Za-z0-9_.-]{0,63})?(?!\n)$",
                                     description="a saved map's name, or empty for the map saved last")] = ""


class JogRequest(msgspec.Struct, forbid_unknown_fields=True):
    """Body twist: vx, vy (m/s), wz (rad/s)."""

    vx: Speed = 0.0
    vy: Speed = 0.0
    wz: Speed = 0.0


class JogReply(msgspec.Struct):
    ok: bool
    vx: float
    vy: float
    wz: float
    clamped: bool
    timeout_s: float


class PoseIn(msgspec.Struct, forbid_unknown_fields=True):
    """A map-frame pose: x, y (m), theta (rad)."""

    x: Coord
    y: Coord
    theta: Angle = 0.0


class PoseCreate(msgspec.Struct, forbid_unknown_fields=True):
    """{name, x, y, theta}, or {name, from_current: true} to teach the robot's current map pose."""

    name: Name
    x: Coord | None = None
    y: Coord | None = None
    theta: Angle | None = None
    from_current: bool = False


class PosePatch(msgspec.Struct, forbid_unknown_fields=True):
    name: Name | None = None
    x: Coord | None = None
    y: Coord | None = None
    theta: Angle | None = None


class MoveRequest(msgspec.Struct, forbid_unknown_fields=True):
    direction: Literal["up", "down"]


class PoseItem(msgspec.Struct, forbid_unknown_fields=True):
    name: Name
    x: Coord
    y: Coord
    theta: Angle = 0.0


class ImportRequest(msgspec.Struct, forbid_unknown_fields=True):
    """The document ``GET /api/poses/export`` returns; ``replace`` deletes the current list first."""

    poses: Annotated[list[PoseItem], msgspec.Meta(max_length=10000)]
    format: Literal["zagv-poses"] = "zagv-poses"
    version: Literal[1] = 1
    replace: bool = False


class GoalAccepted(msgspec.Struct):
    accepted: bool
    goal_id: str
    reason: str = ""


login, logout = session_routes("Log in with the HMI password; returns a bearer token")


def _backend(request: Request | WebSocket) -> Backend:
    return request.app.state.backend


# ---------------------------------------------------------------------------------------------- handlers


@get("/status", summary="Odometry, map pose, wheel states, nav status, service health")
async def status(request: Request) -> dict:
    return _backend(request).status()


@get("/robot", summary="Robot facts the HMI needs: velocity limits, footprint, home pose, jog timing")
async def robot_info(request: Request) -> dict:
    b = _backend(request)
    r, c = b.robot, b.config
    return {"robot_id": r.robot_id, "chassis_radius_m": r.chassis_radius_m,
            "modules": [{"x": m.x_m, "y": m.y_m} for m in r.modules],
            "limits": {"vx_min_mps": r.vx_min_mps, "vx_max_mps": r.vx_max_mps, "vy_max_mps": r.vy_max_mps,
                       "wz_max_radps": r.wz_max_radps},
            "laser": {"x": r.laser_mount_x_m, "y": r.laser_mount_y_m, "theta": r.laser_mount_theta_rad},
            "home": {"x": c.home_x_m, "y": c.home_y_m, "theta": c.home_theta_rad},
            "jog_timeout_s": c.jog_timeout_s, "ws_rate_hz": c.ws_rate_hz}


def _drive_handler(action: str, summary: str):  # a Litestar route handler
    async def handler(request: Request) -> ActionReply:
        b = _backend(request)
        reply = await (b.estop() if action == "estop" else b.drive(action))
        return ActionReply(ok=True, message=reply.message or action)

    handler.__name__ = f"drive_{action}"
    return post(f"/drive/{action}", status_code=HTTP_200_OK, summary=summary, name=f"drive_{action}")(handler)


drive_enable = _drive_handler("enable", "Enable the drive (motors powered, commands followed)")
drive_disable = _drive_handler("disable", "Disable the drive (motors unpowered)")
drive_estop = _drive_handler("estop", "Emergency stop: drive latched stopped, jog ended, navigation canceled")
drive_release = _drive_handler("release", "Release the e-stop latch (enable again to move)")


@post("/jog", status_code=HTTP_200_OK,
      summary="Jog (dead-man): keep sending at least every 0.3 s; motion stops when requests stop")
async def jog(request: Request, data: JogRequest) -> JogReply:
    b = _backend(request)
    vx, vy, wz = b.jog_command(data.vx, data.vy, data.wz)
    clamped = any(not math.isclose(a, c, abs_tol=1e-12) for a, c in zip((data.vx, data.vy, data.wz), (vx, vy, wz)))
    return JogReply(ok=True, vx=vx, vy=vy, wz=wz, clamped=clamped, timeout_s=b.config.jog_timeout_s)


@post("/goal", status_code=HTTP_200_OK, summary="Navigate to a map pose")
async def goal(request: Request, data: PoseIn) -> GoalAccepted:
    r = await _backend(request).goal(data.x, data.y, data.theta)
    return GoalAccepted(accepted=True, goal_id=r.goal_id)


@post("/goal/cancel", status_code=HTTP_200_OK)
async def goal_cancel(request: Request) -> ActionReply:
    r = await _backend(request).cancel()
    return ActionReply(ok=True, message=r.message or "canceled")


@post("/home", status_code=HTTP_200_OK, summary="Navigate to the start pose (hmi_api.home_*)")
async def home(request: Request) -> GoalAccepted:
    b = _backend(request)
    c = b.config
    r = await b.goal(c.home_x_m, c.home_y_m, c.home_theta_rad, f"home-{uuid.uuid4().hex[:6]}")
    return GoalAccepted(accepted=True, goal_id=r.goal_id)


@post("/initial_pose", status_code=HTTP_200_OK, summary="Set the localization estimate")
async def initial_pose(request: Request, data: PoseIn) -> ActionReply:
    r = await _backend(request).initial_pose(data.x, data.y, data.theta)
    return ActionReply(ok=True, message=r.message or "initial pose set")


@post("/mapping/start", status_code=HTTP_200_OK, summary="Start building a new map (SLAM) from the current pose")
async def mapping_start(request: Request) -> ActionReply:
    r = await _backend(request).mapping_mode("mapping")
    return ActionReply(ok=True, message=r.message or "mapping")


@post("/mapping/save", status_code=HTTP_200_OK, summary="Save the map being built (ROS map_server YAML + PGM)")
async def mapping_save(request: Request, data: MapSaveIn) -> ActionReply:
    r = await _backend(request).save_map(data.name)
    return ActionReply(ok=True, message=r.message)


@post("/mapping/stop", status_code=HTTP_200_OK, summary="Stop mapping; localize (AMCL) on a saved map")
async def mapping_stop(request: Request, data: MapStopIn) -> ActionReply:
    r = await _backend(request).mapping_mode("navigation", data.map)
    return ActionReply(ok=True, message=r.message or "navigation")


@get("/map", summary="Map metadata and the map image (PNG, base64)")
async def map_json(request: Request) -> dict:
    b = _backend(request)
    meta = b.map_meta()
    png = b.map_png()
    if png is not None:
        meta["png_base64"] = base64.b64encode(png).decode()
    return meta


@get("/map.png", media_type="image/png", opt={TOKEN_IN_QUERY: True},
     summary="The map image (north up; pixel (0,0) is the top-left)")
async def map_png(request: Request) -> Response[bytes]:
    png = _backend(request).map_png()
    if png is None:
        raise RobotUnavailable("no map yet: localization has not published one")
    return Response(png, media_type="image/png")


@get("/velocities", summary="Recorded commanded and measured velocities (last window_s seconds)")
async def velocities(request: Request, window_s: Annotated[float, msgspec.Meta(gt=0, le=1e6)] = 60.0) -> dict:
    if not (math.isfinite(window_s) and 0 < window_s <= 1e6):  # the declared bounds let NaN through
        raise ValidationException("window_s must be a number of seconds in (0, 1e6]",
                                  extra=[{"key": "window_s", "source": "query"}])
    b = _backend(request)
    return {"columns": list(b.recorder.COLUMNS), "rows": b.recorder.window(window_s)}


@get("/velocities.csv", media_type=MediaType.TEXT, opt={TOKEN_IN_QUERY: True},
     summary="All recorded velocities as CSV")
async def velocities_csv(request: Request) -> Response[str]:
    text = _backend(request).recorder.csv()
    return Response(text, media_type="text/csv",
                    headers={"content-disposition": 'attachment; filename="zagv-velocities.csv"'})


# ---- poses


@get("/poses", summary="The pose list, in order")
async def poses_list(request: Request) -> list[PoseRecord]:
    b = _backend(request)
    return await b.db_call(b.db.list)


@post("/poses", summary="Add a pose, or teach the current one with from_current")
async def poses_add(request: Request, data: PoseCreate) -> PoseRecord:
    b = _backend(request)
    if data.from_current:
        if data.x is not None or data.y is not None or data.theta is not None:
            raise ValidationException("give either x, y, theta or from_current, not both")
        pose = b.view.map_pose()
        if pose is None:
            raise RobotRejected("no current map pose to teach: localization has not published one")
        x, y, theta = pose
    else:
        missing = [k for k in ("x", "y", "theta") if getattr(data, k) is None]
        if missing:
            raise ValidationException(f"missing {', '.join(missing)} (or send from_current: true)")
        assert data.x is not None and data.y is not None and data.theta is not None
        x, y, theta = data.x, data.y, data.theta
    return await b.db_call(b.db.add, data.name, x, y, theta)


@get("/poses/export", opt={TOKEN_IN_QUERY: True}, summary="The pose list as an import document")
async def poses_export(request: Request) -> dict:
    b = _backend(request)
    return await b.db_call(b.db.export)


@post("/poses/import", status_code=HTTP_200_OK, summary="Append (or replace with) an exported pose list")
async def poses_import(request: Request, data: ImportRequest) -> list[PoseRecord]:
    b = _backend(request)
    items = [(p.name, p.x, p.y, p.theta) for p in data.poses]
    return await b.db_call(b.db.import_poses, items, replace=data.replace)


@post("/poses/run", status_code=HTTP_200_OK, summary="Run the whole list as a waypoint sequence")
async def poses_run(request: Request) -> GoalAccepted:
    b = _backend(request)
    poses = await b.db_call(b.db.list)
    r = await b.run_poses(poses)
    return GoalAccepted(accepted=True, goal_id=r.goal_id)


@patch("/poses/{pose_id:int}")
async def poses_patch(request: Request, pose_id: int, data: PosePatch) -> PoseRecord:
    b = _backend(request)
    return await b.db_call(b.db.update, pose_id, name=data.name, x=data.x, y=data.y, theta=data.theta)


@delete("/poses/{pose_id:int}", status_code=HTTP_200_OK)
async def poses_delete(request: Request, pose_id: int) -> ActionReply:
    b = _backend(request)
    await b.db_call(b.db.delete, pose_id)
    return ActionReply(ok=True, message=f"pose {pose_id} deleted")


@post("/poses/{pose_id:int}/move", status_code=HTTP_200_OK, summary="Move a pose up or down the list")
async def poses_move(request: Request, pose_id: int, data: MoveRequest) -> list[PoseRecord]:
    b = _backend(request)
    return await b.db_call(b.db.move, pose_id, data.direction)


@post("/poses/{pose_id:int}/send", status_code=HTTP_200_OK, summary="Navigate to this pose")
async def poses_send(request: Request, pose_id: int) -> GoalAccepted:
    b = _backend(request)
    pose = await b.db_call(b.db.get, pose_id)
    r = await b.send_pose(pose)
    return GoalAccepted(accepted=True, goal_id=r.goal_id)


@websocket("/ws", opt={TOKEN_IN_QUERY: True})
async def ws(socket: WebSocket) -> None:
    """Streams JSON frames at ``ws_rate_hz``: {type: "tick", status, scan, vel, paths?, particles?}; closes with
    code 1008 once its token is revoked (logout) or expires.

    Pacing uses wall time (asyncio.sleep): the frames feed a display that a person watches in real time.
    """
    b: Backend = socket.app.state.backend
    token = bearer_token(socket, query_allowed=True)
    await socket.accept()
    period = 1.0 / b.config.ws_rate_hz
    versions = (-1, -1)
    tick = 0
    loop = asyncio.get_running_loop()
    next_t = loop.time()
    try:
        while True:
            if not b.tokens.valid(token):
                await socket.close(code=1008, reason="logged out or token expired")
                return
            payload, versions = b.frame(full=tick % 20 == 0, last_versions=versions)
            await socket.send_data(payload.decode(), mode="text")
            tick += 1
            next_t += period
            delay = next_t - loop.time()
            if delay < -period:
                next_t = loop.time()
            await asyncio.sleep(max(0.0, delay))
    except (WebSocketDisconnect, OSError, RuntimeError):
        return


# ---------------------------------------------------------------------------------------------- errors


def _error(status: int, detail: str, extra: Any = None, headers: dict[str, str] | None = None) -> Response[dict]:
    body: dict[str, Any] = {"status_code": status, "detail": detail}
    if extra:
        body["extra"] = extra
    if status == 401:
        headers = {**(headers or {}), "www-authenticate": 'Bearer realm="zagv"'}
    return Response(body, status_code=status, headers=headers)


def _on_validation(_: Request, exc: ValidationException) -> Response[dict]:
    return _error(422, str(exc.detail), exc.extra)


def _on_client_error(_: Request, exc: ClientException) -> Response[dict]:
    """A body that is not even JSON (e.g. a bare NaN) is a validation failure too: 422, like a wrong type."""
    status = 422 if exc.status_code == 400 else exc.status_code
    return _error(status, str(exc.detail), exc.extra, dict(exc.headers or {}))


def _on_http(_: Request, exc: HTTPException) -> Response[dict]:
    return _error(exc.status_code, str(exc.detail), exc.extra, dict(exc.headers or {}))


def _on_internal(request: Request, exc: Exception) -> Response[dict]:
    """A bug: logged with its traceback; the client gets a 500 without internals."""
    log.error("%s %s failed", request.method, request.url.path, exc_info=exc)
    return _error(500, f"internal error ({type(exc).__name__}); see the hmi_api log")


def _on_not_found(_: Request, exc: PoseNotFound) -> Response[dict]:
    return _error(404, str(exc))


def _on_db_error(_: Request, exc: PoseDbError) -> Response[dict]:
    return _error(422, str(exc))


def _on_storage(request: Request, exc: sqlite3.OperationalError) -> Response[dict]:
    """The pose database cannot be used (file read-only, disk full, locked): 503 naming SQLite's reason."""
    log.error("%s %s: pose database error: %s", request.method, request.url.path, exc)
    return _error(503, f"pose database unavailable: {exc}")


def _on_rejected(_: Request, exc: RobotRejected | PoseListFull) -> Response[dict]:
    return _error(409, str(exc))


def _on_throttled(_: Request, exc: LoginThrottled) -> Response[dict]:
    return _error(429, str(exc), headers={"retry-after": str(max(1, math.ceil(exc.retry_after_s)))})


def _on_undecodable(_: Request, exc: UndecodableBody) -> Response[dict]:
    return _error(400, str(exc.detail))


def _on_unavailable(_: Request, exc: RobotUnavailable) -> Response[dict]:
    return _error(503, f"robot service unavailable: {exc}")


@get("/", include_in_schema=False)
async def index() -> Response[bytes]:
    return Response((STATIC_DIR / "index.html").read_bytes(), media_type=MediaType.HTML)


def create_asgi_app(backend: Backend):  # an ASGI application
    """The Litestar app inside the security layer (Host allow-list, security headers), which also covers requests
    that match no route."""
    return security_layer(backend.config.host_allow_list())(create_app(backend))


def create_app(backend: Backend) -> Litestar:
    api = Router(
        path="/api",
        guards=[require_token],
        route_handlers=[
            logout, status, robot_info, drive_enable, drive_disable, drive_estop, drive_release, jog, goal,
            goal_cancel, home, initial_pose, mapping_start, mapping_save, mapping_stop, map_json, map_png, velocities,
            velocities_csv, poses_list, poses_add,
            poses_export, poses_import, poses_run, poses_patch, poses_delete, poses_move, poses_send, ws,
            *blackbox.ROUTES,
        ],
        security=[{"BearerToken": []}],
        before_request=strict_body,
    )
    public = Router(path="/api", route_handlers=[login], before_request=strict_body)
    docs = Router(path="/api/schema", guards=[require_token], route_handlers=[], include_in_schema=False)
    app = Litestar(
        route_handlers=[public, api, index,
                        create_static_files_router(path="/static", directories=[STATIC_DIR],
                                                   include_in_schema=False)],
        exception_handlers={
            ValidationException: _on_validation,
            ClientException: _on_client_error,
            HTTPException: _on_http,
            Exception: _on_internal,
            UndecodableBody: _on_undecodable,
            PoseNotFound: _on_not_found,
            PoseListFull: _on_rejected,
            PoseDbError: _on_db_error,
            LoginThrottled: _on_throttled,
            sqlite3.OperationalError: _on_storage,
            RobotRejected: _on_rejected,
            RobotUnavailable: _on_unavailable,
        },
        openapi_config=OpenAPIConfig(
            title="zagv HMI API", version="1.0.0", path="/api/schema", openapi_router=docs,
            render_plugins=[JsonRenderPlugin()],
            components=Components(security_schemes={
                "BearerToken": SecurityScheme(type="http", scheme="bearer",
                                              description="token from POST /api/login")}),
        ),
        debug=False,
        logging_config=None,
    )
    app.state.backend = backend
    return app
