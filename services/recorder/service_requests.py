"""Recorded service requests issued again during a replay (core, no I/O): rosbag2's ``--publish-service-requests``.

A service that records its requests publishes ``<query>/_service_event`` (``services/common/service_events.py``):
``request_received`` with the request, ``response_sent`` with the input message it was served on. ``collect`` pairs
them into ``RecordedRequest`` s; ``RequestSchedule.due`` says which to issue before each message a replay publishes:

- a request served on an input (``localization/nomotion``: the update ran on the scan stamped ``input_stamp``) just
  before the first played message of ``input_topic`` stamped at or after ``input_stamp`` (compared in nanoseconds, as
  a bag holds stamps), so that it takes effect on the same message as it did live (the replay waits for the
  service's ``request_received`` before going on);
- any other request (no response recorded, or its input topic is not played) before the first message logged at or
  after its ``request_received`` event, as rosbag2 does.

A request whose type says on which scan it is to take effect (``at_scan_stamp``: ``localization/initial_pose``) is
issued again with the stamp of the scan it was served on live (``replay_payload``): the service applies it just
before that scan however many earlier scans are still on their way, which issuing it at the right point of the
stream alone does not guarantee.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import msgspec

from proto import codec
from proto.messages import ServiceEvent
from services.common.service_events import query_of
from services.recorder.rosconv import stamp_to_ns

if TYPE_CHECKING:
    from services.recorder.source import BagSource


@dataclass
class RecordedRequest:
    """One request as recorded: its query, payload, log time (ns) and the input it was served on (if any)."""

    query: str
    sequence: int
    request: bytes
    log_ns: int
    input_topic: str = ""
    input_stamp_s: float = 0.0
    received_stamp_s: float = 0.0  # the service's clock when it took the request (its request_received event)


def replay_payload(req: RecordedRequest) -> bytes:
    """The payload to issue ``req`` again with: its recorded request, with ``at_scan_stamp`` set to the scan it was
    served on and ``stamp`` to when the service took it live, where its type has those fields."""
    req_type, _ = codec.query_types(req.query)
    fields = req_type.__struct_fields__
    changes: dict[str, float] = {}
    if req.input_topic == "scan" and req.input_stamp_s > 0 and "at_scan_stamp" in fields:
        changes["at_scan_stamp"] = req.input_stamp_s
    if req.received_stamp_s > 0 and "stamp" in fields:
        changes["stamp"] = req.received_stamp_s
    if not changes:
        return req.request
    try:
        msg = codec.decode_as(req_type, req.request)
    except codec.ProtoDecodeError:  # issued as recorded: the service refuses it with the reason
        return req.request
    return codec.encode(msgspec.structs.replace(msg, **changes))


def collect(events: Iterable[tuple[int, str, ServiceEvent]]) -> list[RecordedRequest]:
    """``(log_ns, topic, event)`` in log order -> the recorded requests in log order. A response is paired with the
    latest request of its query and sequence (a restarted service numbers from 1 again)."""
    requests: list[RecordedRequest] = []
    latest: dict[tuple[str, int], RecordedRequest] = {}
    for log_ns, topic, ev in events:
        query = query_of(topic)
        if query is None:
            continue
        if ev.event == "request_received":
            received = RecordedRequest(query, ev.sequence, ev.request, log_ns, received_stamp_s=ev.stamp)
            requests.append(received)
            latest[(query, ev.sequence)] = received
        elif (answered := latest.get((query, ev.sequence))) is not None and ev.input_topic and ev.input_stamp > 0:
            answered.input_topic, answered.input_stamp_s = ev.input_topic, ev.input_stamp
    return requests


class RequestSchedule:
    """The recorded requests still to issue, handed out by ``due`` as the replay goes through the bag."""

    def __init__(self, requests: list[RecordedRequest], played_topics: set[str] | None) -> None:
        """``played_topics``: topics the replay publishes (None: all); a request anchored on a topic that is not
        played falls back to its log time."""
        self.anchored = [r for r in requests if r.input_topic and (played_topics is None
                                                                   or r.input_topic in played_topics)]
        self.timed = sorted((r for r in requests if r not in self.anchored), key=lambda r: r.log_ns)
        self.anchored.sort(key=lambda r: r.input_stamp_s)

    def __len__(self) -> int:
        return len(self.anchored) + len(self.timed)

    def due(self, log_ns: int, topic: str, stamp_s: float | None) -> list[RecordedRequest]:
        """The requests to issue before publishing the message of ``topic`` logged at ``log_ns`` with header stamp
        ``stamp_s`` (None: it has none), in the order they were recorded."""
        out = []
        while self.timed and self.timed[0].log_ns <= log_ns:
            out.append(self.timed.pop(0))
        if stamp_s is not None:
            keep: list[RecordedRequest] = []
            stamp_ns = stamp_to_ns(stamp_s)  # a bag holds stamps to the nanosecond
            for r in self.anchored:
                (out if r.input_topic == topic and stamp_to_ns(r.input_stamp_s) <= stamp_ns else keep).append(r)
            self.anchored = keep
        return sorted(out, key=lambda r: r.log_ns)

    def rest(self) -> list[RecordedRequest]:
        """Requests never due (their input lies past the end of the replay), in log order; clears them."""
        out = sorted(self.anchored + self.timed, key=lambda r: r.log_ns)
        self.anchored, self.timed = [], []
        return out


def recorded_requests(source: BagSource, start_ns: int, end_ns: int) -> list[RecordedRequest]:
    """The service requests recorded in the bag's ``_service_event`` topics within [start_ns, end_ns]."""
    names = {t.lstrip("/") for t in source.topics if query_of(t.lstrip("/")) is not None}
    if not names:
        return []
    return collect((t_ns, name, msg) for t_ns, name, msg in source.messages(start_ns, end_ns, names)
                   if isinstance(msg, ServiceEvent))
