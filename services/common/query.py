"""Queries that wait for their answerer: one place for every query client (services, CLI, HMI, adapters).

Zenoh completes a ``get`` at once when no queryable matches its key, so a client that starts before (or restarts
faster than) the service it asks would fail at once whatever its timeout. ``query`` therefore retries with
exponential back-off (``FIRST_RETRY_S`` doubling up to ``MAX_RETRY_S``) until its deadline while nothing answered;
an answer (a reply, a refusal, an error reply or a payload that does not decode) ends it. The error names the key,
how long it really waited and how many times it asked. Waiting is on the wall clock (``time.monotonic``): it is
about the link, not the robot, and must work while a simulator's clock is stopped.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from typing import Any

import zenoh

from proto import codec
from proto.keys import Keys
from proto.messages import Message

FIRST_RETRY_S = 0.05
MAX_RETRY_S = 0.5


class QueryError(RuntimeError):
    """A query that got no usable reply (timeout, no queryable, an error reply or a bad payload)."""


class NoAnswer(QueryError):
    """No queryable answered before the deadline (``waited_s`` of wall time over ``attempts`` tries)."""

    def __init__(self, key: str, waited_s: float, attempts: int, matched: bool) -> None:
        what = "a queryable matched but sent no reply" if matched else "no queryable answered"
        super().__init__(f"no reply to {key} ({what}; waited {waited_s:.1f} s, {attempts} attempt"
                         f"{'s' if attempts != 1 else ''})")
        self.key = key
        self.waited_s = waited_s
        self.attempts = attempts


#: the error payload Zenoh delivers when a get's timeout ran out before the queryable answered
ZENOH_TIMEOUT = "Timeout"


def _get_once(session: zenoh.Session, key: str, payload: bytes, timeout_s: float, rep_type: type,
              loop: asyncio.AbstractEventLoop) -> asyncio.Future[tuple[str, Any]]:
    """One ``get``: resolves to ("reply", msg), ("error", QueryError) or ("none", None) when it ended unanswered."""
    fut: asyncio.Future[tuple[str, Any]] = loop.create_future()

    def settle(value: tuple[str, Any]) -> None:
        if not fut.done():
            fut.set_result(value)

    def deliver(value: tuple[str, Any]) -> None:  # Zenoh's thread; the caller's loop may be gone (it exited)
        with contextlib.suppress(RuntimeError):
            loop.call_soon_threadsafe(settle, value)

    def on_reply(reply: zenoh.Reply) -> None:
        if reply.ok is not None:
            try:
                msg: Any = codec.decode_as(rep_type, reply.ok.payload.to_bytes(), key)
                deliver(("reply", msg))
            except codec.ProtoDecodeError as exc:
                deliver(("error", QueryError(str(exc))))
        else:
            text = reply.err.payload.to_bytes().decode(errors="replace") if reply.err is not None else "no reply"
            if text == ZENOH_TIMEOUT:  # Zenoh's own reply when the get's timeout ran out: nothing answered in time
                deliver(("none", None))
            else:
                deliver(("error", QueryError(f"{key}: {text}")))

    def on_done() -> None:
        deliver(("none", None))

    # no consolidation: the first reply is delivered at once, not held until the queryable's final message
    session.get(key, zenoh.handlers.Callback(on_reply, on_done), payload=payload, timeout=max(timeout_s, 0.01),
                consolidation=zenoh.ConsolidationMode.NONE)
    return fut


async def query(
    session: zenoh.Session, keys: Keys, name: str, request: Message | None = None, *, timeout_s: float = 2.0
) -> Any:
    """Query ``name`` and return the first reply decoded as its registered reply type.

    Retries with back-off while no queryable answered, until ``timeout_s`` (wall time) has passed; raises
    ``NoAnswer`` then, or ``QueryError`` for an error reply or an undecodable one.
    """
    req_type, rep_type = codec.query_types(name)
    key = keys(name)
    payload = codec.encode(request if request is not None else req_type())
    loop = asyncio.get_running_loop()
    started = time.monotonic()
    deadline = started + timeout_s
    retry_s = FIRST_RETRY_S
    attempts = 0
    matched = False
    while True:
        attempts += 1
        sent = time.monotonic()
        kind, value = await _get_once(session, key, payload, deadline - sent, rep_type, loop)
        if kind == "reply":
            return value
        if kind == "error":
            raise value
        now = time.monotonic()
        # an unanswered get that lasted its whole timeout reached a queryable that never replied
        matched = matched or now - sent >= max(0.1, 0.9 * (deadline - sent))
        if now >= deadline:
            raise NoAnswer(key, now - started, attempts, matched)
        await asyncio.sleep(min(retry_s, deadline - now))
        retry_s = min(retry_s * 2.0, MAX_RETRY_S)
