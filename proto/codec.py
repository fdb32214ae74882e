"""One codec for every key: msgpack through msgspec, the key naming the type (docs/architecture.md).

>>> payload = encode(Twist2D(vx=0.1))
>>> decode("cmd_vel", payload).vx
0.1
"""

from __future__ import annotations

import contextlib
from functools import cache
from typing import Any, TypeVar

import msgspec
import numpy as np

from proto import messages as m
from proto.keys import split_key
from proto.registry import QUERIES, TOPICS

T = TypeVar("T", bound=m.Message)

_encoder = msgspec.msgpack.Encoder()


class ProtoDecodeError(ValueError):
    """A payload that does not decode as the type its key carries. ``key`` and ``type_name`` say which."""

    def __init__(self, key: str, type_name: str, reason: str) -> None:
        super().__init__(f"bad payload on {key!r} (expected {type_name}): {reason}")
        self.key = key
        self.type_name = type_name
        self.reason = reason


def encode(msg: m.Message) -> bytes:
    """msgpack bytes of a message."""
    return _encoder.encode(msg)


@cache
def _decoder(t: type[T]) -> msgspec.msgpack.Decoder:
    return msgspec.msgpack.Decoder(t)


def decode_as(t: type[T], payload: bytes | bytearray | memoryview, key: str = "?") -> T:
    """Decode ``payload`` as ``t``; raises ProtoDecodeError naming the key, the type and the problem."""
    try:
        return _decoder(t).decode(payload)
    except (msgspec.DecodeError, msgspec.ValidationError) as exc:
        raise ProtoDecodeError(key, t.__name__, str(exc)) from None


def topic_type(name: str) -> type[m.Message]:
    """Payload type of a topic name (``scan``) or full key (``agv/r1/scan``)."""
    if name in TOPICS:
        return TOPICS[name]
    try:
        _, short = split_key(name)
    except ValueError:
        short = name
    if short in TOPICS:
        return TOPICS[short]
    raise KeyError(f"no message type is registered for key {name!r}")


def decode(name: str, payload: bytes | bytearray | memoryview) -> m.Message:
    """Decode a topic payload by its key (short name or full key expression)."""
    return decode_as(topic_type(name), payload, key=name)


def query_types(name: str) -> tuple[type[m.Message], type[m.Message]]:
    """(request, reply) types of a query name or full key."""
    if name not in QUERIES:
        with contextlib.suppress(ValueError):
            _, name = split_key(name)
    if name in QUERIES:
        return QUERIES[name]
    raise KeyError(f"no query is registered for key {name!r}")


def array(msg: m.Message, field: str) -> np.ndarray:
    """Zero-copy numpy view of a bytes field declared in ``ARRAY_FIELDS`` (shape (n,) or (n, cols))."""
    dtype, cols = type(msg).ARRAY_FIELDS[field]
    raw = getattr(msg, field)
    a = np.frombuffer(raw, dtype=dtype)
    return a if cols == 1 else a.reshape(-1, cols)


def to_display(msg: Any) -> Any:
    """Builtin (JSON-ready) form of a message where array bytes fields become lists of numbers."""
    if isinstance(msg, m.Message):
        out: dict[str, Any] = {}
        arrays = type(msg).ARRAY_FIELDS
        for f in msg.__struct_fields__:
            v = getattr(msg, f)
            if f in arrays:
                a = array(msg, f)
                values = a.tolist()
                if a.ndim == 1 and a.dtype.kind == "f":
                    values = [x if np.isfinite(x) else None for x in values]
                out[f] = values
            else:
                out[f] = to_display(v)
        return out
    if isinstance(msg, list):
        return [to_display(v) for v in msg]
    if isinstance(msg, float) and not np.isfinite(msg):
        return None
    return msg


def to_json(msg: m.Message) -> str:
    """One-line JSON of a message (arrays expanded, non-finite numbers as null)."""
    return msgspec.json.encode(to_display(msg)).decode()


def decode_any(key: str, payload: bytes) -> m.Message:
    """Decode by key, trying query reply/request types for query keys."""
    try:
        return decode(key, payload)
    except KeyError:
        req, rep = query_types(key)
        try:
            return decode_as(rep, payload, key)
        except ProtoDecodeError:
            return decode_as(req, payload, key)
