"""What every web HMI of zagv (the robot's hmi_api, the site's fleet view) enforces on its HTTP API.

- login: ``Authorization: Bearer <token>`` on every route but the login; only routes marked ``opt={TOKEN_IN_QUERY:
  True}`` (WebSockets, GET downloads) may pass ``?token=`` instead, as browsers cannot set headers there
  (:func:`require_token` checks ``app.state.backend.tokens``, a :class:`services.common.auth.TokenStore`);
- bodies: JSON only (415 otherwise), UTF-8 (400), decoded strictly against the handler's type (422) before
  Litestar's lax conversion (:func:`strict_body`);
- the session routes ``POST /login`` and ``POST /logout`` (:func:`session_routes`), the same on both;
- every response: same-origin Content-Security-Policy, no framing, no MIME sniffing, no referrer; a ``Host`` outside
  the allow-list gets 400 (DNS rebinding), WebSockets too (:func:`security_layer`).
"""

from __future__ import annotations

import asyncio
from typing import Annotated

import msgspec
from litestar import Request, post
from litestar.connection import ASGIConnection
from litestar.exceptions import ClientException, HTTPException, NotAuthorizedException, ValidationException
from litestar.handlers.base import BaseRouteHandler
from litestar.handlers.http_handlers import HTTPRouteHandler
from litestar.status_codes import HTTP_200_OK

#: security headers of every response: nothing from another origin, no framing, no MIME sniffing, no referrer
SECURITY_HEADERS = {
    "content-security-policy": "default-src 'self'; img-src 'self' data: blob:; connect-src 'self'; "
                               "object-src 'none'; base-uri 'none'; frame-ancestors 'none'; form-action 'self'",
    "x-frame-options": "DENY",
    "x-content-type-options": "nosniff",
    "referrer-policy": "no-referrer",
}
#: the query parameter a route may take the token from (``opt`` key of its handler)
TOKEN_IN_QUERY = "token_in_query"


class UndecodableBody(ClientException):
    """A body that is not UTF-8: 400 (422 is for JSON that does not validate)."""

    status_code = 400


def bearer_token(connection: ASGIConnection, *, query_allowed: bool = False) -> str | None:
    """The token of ``Authorization: Bearer``, or of ``?token=`` where ``query_allowed`` (WebSocket, downloads)."""
    header = connection.headers.get("authorization", "")
    if header.lower().startswith("bearer "):
        return header[7:].strip()
    return connection.query_params.get("token") if query_allowed else None


def require_token(connection: ASGIConnection, handler: BaseRouteHandler) -> None:
    backend = connection.app.state.backend
    if not backend.tokens.valid(bearer_token(connection, query_allowed=bool(handler.opt.get(TOKEN_IN_QUERY)))):
        raise NotAuthorizedException("login first: POST /api/login, then send Authorization: Bearer <token>")


async def strict_body(request: Request) -> None:
    """Decode the JSON body strictly against the handler's ``data`` type before Litestar's own (lax) conversion,
    so that ``"0.1"`` for a number or ``true`` for a float is a 422, not silently converted. A body must be
    ``application/json`` (415 otherwise: no form posts) and UTF-8 (400 otherwise)."""
    data_field = request.route_handler.parsed_data_field
    if data_field is None:
        return None
    media_type = request.headers.get("content-type", "").split(";", 1)[0].strip().lower()
    if media_type != "application/json":
        raise HTTPException(status_code=415, detail=f"the body must be application/json, not {media_type[:60]!r}")
    body = await request.body()
    try:
        body.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise UndecodableBody(f"the body is not UTF-8 (byte {exc.start})") from None
    try:
        msgspec.json.decode(body, type=data_field.annotation, strict=True)
    except (msgspec.DecodeError, msgspec.ValidationError) as exc:
        raise ValidationException(f"invalid request body: {exc}") from None
    return None


def host_name(host_header: str) -> str:
    """The name part of a Host header: ``127.0.0.1:8080`` -> ``127.0.0.1``, ``[::1]:8080`` -> ``[::1]``."""
    host = host_header.strip().lower()
    if host.startswith("["):
        return host[:host.index("]") + 1] if "]" in host else host
    return host.rsplit(":", 1)[0] if host.count(":") == 1 else host


def security_layer(allowed_hosts: list[str]):
    """ASGI middleware: refuse a Host outside ``allowed_hosts`` (400, DNS rebinding; WebSockets too) and add
    ``SECURITY_HEADERS`` to every HTTP response, error responses and static files included."""
    allowed = {h.lower() for h in allowed_hosts}
    extra = [(k.encode(), v.encode()) for k, v in SECURITY_HEADERS.items()]
    refusal = msgspec.json.encode({"status_code": 400, "detail": "Host header not allowed (hmi_api.allowed_hosts)"})

    def factory(app):
        async def middleware(scope, receive, send) -> None:
            if scope["type"] not in ("http", "websocket"):
                await app(scope, receive, send)
                return
            host = next((v.decode("latin-1") for k, v in scope.get("headers", []) if k == b"host"), "")
            if host_name(host) not in allowed:
                if scope["type"] == "websocket":
                    await send({"type": "websocket.close", "code": 1008})
                    return
                await send({"type": "http.response.start", "status": 400,
                            "headers": [(b"content-type", b"application/json"), *extra]})
                await send({"type": "http.response.body", "body": refusal})
                return
            if scope["type"] != "http":
                await app(scope, receive, send)
                return

            async def send_with_headers(message) -> None:
                if message["type"] == "http.response.start":
                    names = {k.lower() for k, _ in message.get("headers", [])}
                    message["headers"] = [*message.get("headers", []), *(h for h in extra if h[0] not in names)]
                await send(message)

            await app(scope, receive, send_with_headers)

        return middleware

    return factory


class LoginRequest(msgspec.Struct, forbid_unknown_fields=True):
    password: Annotated[str, msgspec.Meta(max_length=1024)]


class LoginReply(msgspec.Struct):
    token: str
    expires_in_s: float


class ActionReply(msgspec.Struct):
    ok: bool
    message: str = ""


#: extra wait after a wrong password, on top of the throttle: slows guessing a little more
WRONG_PASSWORD_DELAY_S = 0.5


def session_routes(login_summary: str) -> tuple[HTTPRouteHandler, HTTPRouteHandler]:
    """``POST /login`` (a bearer token for the right password, 401 for a wrong one) and ``POST /logout`` (the token
    revoked), on ``app.state.backend``: its ``login(password, client)``, ``tokens`` and ``config.token_ttl_s``."""

    @post("/login", status_code=HTTP_200_OK, summary=login_summary)
    async def login(request: Request, data: LoginRequest) -> LoginReply:
        backend = request.app.state.backend
        token = await backend.login(data.password, request.client.host if request.client else "unknown")
        if token is None:
            await asyncio.sleep(WRONG_PASSWORD_DELAY_S)
            raise NotAuthorizedException("wrong password")
        return LoginReply(token=token, expires_in_s=backend.config.token_ttl_s)

    @post("/logout", status_code=HTTP_200_OK)
    async def logout(request: Request) -> ActionReply:
        token = bearer_token(request)
        if token:
            request.app.state.backend.tokens.revoke(token)
        return ActionReply(ok=True, message="logged out")

    return login, logout
