"""The live side of re-issuing recorded service requests during a replay (``zagv replay``; the plan is
``service_requests.py``): send each on the robot's session, wait until the service has taken it (its own
``request_received`` event), and count the requests served on the same input message as they were live."""

from __future__ import annotations

import collections
import contextlib
import threading
import time

import zenoh

from proto import codec
from proto.messages import ServiceEvent
from services.common.service_events import event_topic
from services.recorder.service_requests import RecordedRequest, replay_payload

#: wall s a re-issued request's reply may take after the service took it (localization/nomotion answers on the next
#: scan, which the replay publishes only once the request was taken)
NOMOTION_REPLY_S = 30.0


def _ignore_reply(_reply: zenoh.Reply) -> None:
    """The replies of re-issued requests: the service's own events say what it did."""


class ServiceRequester:
    """Issues recorded requests on the live session and waits until the service has taken each one (its own
    ``request_received`` event); counts the requests served on the same input message as they were live."""

    def __init__(self, session: zenoh.Session, keys, queries: set[str], timeout_s: float) -> None:  # Keys
        self.session, self.keys, self.timeout_s = session, keys, timeout_s
        self.cond = threading.Condition()
        self.received: dict[str, int] = dict.fromkeys(queries, 0)
        self.pending: dict[tuple[str, int], RecordedRequest] = {}  # (query, live sequence) -> the recorded one
        self.issued = collections.Counter[str]()
        self.same_input = collections.Counter[str]()
        self.answered = collections.Counter[str]()
        self.not_taken = collections.Counter[str]()
        self.subs = [session.declare_subscriber(keys(event_topic(q)), self._on_event(q)) for q in sorted(queries)]

    def _on_event(self, query: str):
        def on_sample(sample: zenoh.Sample) -> None:
            try:
                ev = codec.decode_as(ServiceEvent, sample.payload.to_bytes())
            except codec.ProtoDecodeError:
                return
            with self.cond:
                if ev.event == "request_received":
                    self.received[query] += 1
                    self.cond.notify_all()
                elif (req := self.pending.pop((query, ev.sequence), None)) is not None:
                    self.answered[query] += 1
                    if req.input_topic and ev.input_topic == req.input_topic \
                            and abs(ev.input_stamp - req.input_stamp_s) < 1e-6:
                        self.same_input[query] += 1
                    self.cond.notify_all()
        return on_sample

    def issue(self, req: RecordedRequest) -> None:
        """Send ``req`` (again while no queryable answers) and wait until the service has taken it."""
        deadline = time.monotonic() + self.timeout_s
        with self.cond:
            before = self.received[req.query]
        done = threading.Event()
        retry_s = 0.05
        payload = replay_payload(req)
        while True:
            done.clear()
            self.session.get(self.keys(req.query), zenoh.handlers.Callback(_ignore_reply, done.set),
                             payload=payload, timeout=self.timeout_s + NOMOTION_REPLY_S)
            with self.cond:
                while self.received[req.query] == before and not done.is_set() and time.monotonic() < deadline:
                    self.cond.wait(0.01)
                if self.received[req.query] > before:
                    # the live service numbers its requests from its own start
                    self.pending[(req.query, self.received[req.query])] = req
                    self.issued[req.query] += 1
                    return
            if time.monotonic() >= deadline:  # nothing took it: the service is not running (or too busy)
                self.not_taken[req.query] += 1
                return
            time.sleep(min(retry_s, max(deadline - time.monotonic(), 0.0)))
            retry_s = min(2 * retry_s, 0.5)

    def summary(self, wait_s: float = 5.0) -> str:
        """Waits up to ``wait_s`` for the last answers, then one line per query."""
        deadline = time.monotonic() + wait_s
        with self.cond:
            while self.pending and time.monotonic() < deadline:
                self.cond.wait(0.05)
        parts = []
        for q in sorted(self.received):
            part = (f"{q}: {self.issued[q]} recorded request(s) issued again, {self.answered[q]} answered, "
                    f"{self.same_input[q]} served on the same message as recorded")
            if self.not_taken[q]:
                part += f", {self.not_taken[q]} not taken by any service within {self.timeout_s:g} s"
            parts.append(part)
        return "; ".join(parts)

    def close(self) -> None:
        for sub in self.subs:
            with contextlib.suppress(Exception):
                sub.undeclare()
