"""Service events: what a service publishes on ``<query>/_service_event`` for each request it acts on (core, no I/O).

rosbag2 (Jazzy) records a ROS 2 service's calls from its ``_service_event`` topic (service_msgs/ServiceEventInfo:
REQUEST_RECEIVED, RESPONSE_SENT, a sequence number pairing them) and replays the requests with
``--publish-service-requests``. A zagv service does the same for the queries whose effect a replay must reproduce
(``localization/nomotion``: an update and refinement at rest that the scans alone do not cause): a
``request_received`` event once the request has taken effect, a ``response_sent`` event with the answer and the stamp
of the input it was served on. ``zagv replay`` issues the requests again (``services/recorder/service_requests.py``).
"""

from __future__ import annotations

from proto import codec
from proto.messages import Message, ServiceEvent
from proto.registry import QUERIES, SERVICE_EVENT_SUFFIX


def event_topic(query: str) -> str:
    """The service-event topic of ``query`` (``localization/nomotion`` -> ``localization/nomotion/_service_event``)."""
    if query not in QUERIES:
        raise ValueError(f"{query!r} is not a query")
    return query + SERVICE_EVENT_SUFFIX


def query_of(topic: str) -> str | None:
    """The query whose service-event topic ``topic`` is, or None."""
    if not topic.endswith(SERVICE_EVENT_SUFFIX):
        return None
    query = topic[: -len(SERVICE_EVENT_SUFFIX)]
    return query if query in QUERIES else None


class ServiceEventLog:
    """Numbers the requests of one query and builds their two events."""

    def __init__(self) -> None:
        self.sequence = 0

    def request_received(self, stamp_s: float, request: Message) -> ServiceEvent:
        """The event of a request that has just taken effect; its ``sequence`` identifies it in ``response_sent``."""
        self.sequence += 1
        return ServiceEvent(stamp=stamp_s, event="request_received", sequence=self.sequence,
                            request=codec.encode(request))

    @staticmethod
    def response_sent(stamp_s: float, sequence: int, response: Message, input_topic: str = "",
                      input_stamp_s: float = 0.0) -> ServiceEvent:
        """The event of the answer to request ``sequence``, served on the ``input_topic`` message stamped
        ``input_stamp_s`` (none: empty and 0)."""
        return ServiceEvent(stamp=stamp_s, event="response_sent", sequence=sequence, response=codec.encode(response),
                            input_topic=input_topic, input_stamp=input_stamp_s)
