"""zenoh-cli codec plugin: ``zenoh subscribe -k 'agv/**' --decoder zagv`` prints messages as JSON.

Registered under the entry point groups ``zenoh_cli.codecs.decoders`` / ``encoders`` with the name ``zagv``.
Use a config with ``scouting/multicast/enabled: false`` and an explicit loopback endpoint, e.g.::

    zenoh --mode client --connect tcp/127.0.0.1:7447 --cfg 'scouting/multicast/enabled:false' \\
        subscribe -k 'agv/**' --decoder zagv
"""

from __future__ import annotations

import json

import msgspec

from proto.codec import ProtoDecodeError, decode_any, encode, query_types, to_json, topic_type


def decode(key: object, payload: bytes) -> str:
    """JSON line for a payload on ``key``; unknown keys or bad payloads give a JSON error object."""
    k = str(key)
    try:
        return to_json(decode_any(k, payload))
    except (KeyError, ProtoDecodeError) as exc:
        return json.dumps({"error": str(exc), "bytes": len(payload)})


def encode_from_json(key: object, value: str) -> bytes:
    """msgpack payload for ``key`` from JSON text (topic type, or the request type of a query)."""
    k = str(key)
    try:
        t = topic_type(k)
    except KeyError:
        t = query_types(k)[0]
    return encode(msgspec.json.decode(value.encode(), type=t))
