"""Service events and their replay: numbering, recording in a bag, pairing, and where a replay issues each request."""

from __future__ import annotations

from pathlib import Path

import pytest

from proto import codec
from proto import messages as m
from services.common.service_events import ServiceEventLog, event_topic, query_of
from services.recorder.bag import BagRecorder
from services.recorder.service_requests import (
    RecordedRequest,
    RequestSchedule,
    collect,
    recorded_requests,
    replay_payload,
)
from services.recorder.source import BagSource

TOPIC = "localization/nomotion/_service_event"


def test_event_topics_name_their_query() -> None:
    assert event_topic("localization/nomotion") == TOPIC
    assert query_of(TOPIC) == "localization/nomotion"
    assert query_of("scan") is None and query_of("no/such/query/_service_event") is None
    with pytest.raises(ValueError, match="not a query"):
        event_topic("scan")


def test_event_log_numbers_requests_and_carries_payloads() -> None:
    log = ServiceEventLog()
    first, second = log.request_received(10.0, m.Empty()), log.request_received(11.0, m.Empty())
    assert (first.event, first.sequence, second.sequence) == ("request_received", 1, 2)
    assert codec.decode_as(m.Empty, first.request) == m.Empty()
    answer = m.LocalizationUpdate(ok=True, message="updated")
    sent = log.response_sent(10.5, first.sequence, answer, "scan", 10.48)
    assert (sent.event, sent.sequence, sent.input_topic, sent.input_stamp) == ("response_sent", 1, "scan", 10.48)
    assert codec.decode_as(m.LocalizationUpdate, sent.response) == answer


def _events(*items: tuple[int, m.ServiceEvent]) -> list[tuple[int, str, m.ServiceEvent]]:
    return [(t, TOPIC, ev) for t, ev in items]


def test_collect_pairs_each_response_with_the_latest_request_of_its_sequence() -> None:
    log, restarted = ServiceEventLog(), ServiceEventLog()  # a restarted service numbers from 1 again
    a, b = log.request_received(1.0, m.Empty()), log.request_received(2.0, m.Empty())
    c = restarted.request_received(5.0, m.Empty())
    answer = m.LocalizationUpdate(ok=False, message="no scan")
    reqs = collect(_events(
        (100, a), (150, log.response_sent(1.1, 1, answer, "scan", 1.08)),
        (200, b), (250, log.response_sent(2.1, 2, answer)),  # answered on no input (withdrawn)
        (500, c), (550, restarted.response_sent(5.1, 1, answer, "scan", 5.04)),
    ) + [(600, "scan", c)])  # not a service-event topic: ignored
    assert [(r.sequence, r.log_ns, r.input_topic, r.input_stamp_s) for r in reqs] == [
        (1, 100, "scan", 1.08), (2, 200, "", 0.0), (1, 500, "scan", 5.04)]


def test_schedule_issues_a_request_just_before_the_message_it_was_served_on() -> None:
    served = RecordedRequest("localization/nomotion", 1, b"", log_ns=1_000, input_topic="scan", input_stamp_s=2.0)
    timed = RecordedRequest("localization/nomotion", 2, b"", log_ns=5_000)
    schedule = RequestSchedule([served, timed], {"scan", "odom"})
    assert len(schedule) == 2
    # an odom stamped past the scan comes first in the bag: not the anchor; the scan before it is not either
    assert schedule.due(1_500, "odom", 2.01) == []
    assert schedule.due(1_600, "scan", 1.96) == []
    assert schedule.due(1_700, "scan", 2.0) == [served]
    assert schedule.due(1_800, "scan", 2.04) == []
    # the live stamp had bits that the bag's nanoseconds do not keep: the same scan all the same
    near = RecordedRequest("localization/nomotion", 3, b"", log_ns=2_000, input_topic="scan",
                           input_stamp_s=25.150000000000002)
    assert RequestSchedule([near], None).due(2_100, "scan", 25.15) == [near]
    # no input recorded: at its log time, whatever the topic
    assert schedule.due(4_999, "odom", None) == []
    assert schedule.due(5_000, "odom", None) == [timed]
    assert len(schedule) == 0 and schedule.rest() == []


def test_schedule_falls_back_to_the_log_time_when_the_input_is_not_played() -> None:
    req = RecordedRequest("localization/nomotion", 1, b"", log_ns=1_000, input_topic="scan", input_stamp_s=2.0)
    schedule = RequestSchedule([req], {"odom"})
    assert schedule.due(999, "odom", 2.5) == []
    assert schedule.due(1_000, "odom", 2.5) == [req]
    late = RecordedRequest("localization/nomotion", 2, b"", log_ns=9_000, input_topic="scan", input_stamp_s=9.0)
    schedule = RequestSchedule([late], None)
    assert schedule.due(2_000, "scan", 3.0) == []
    assert schedule.rest() == [late] and len(schedule) == 0  # past the end of the replay: never issued


def test_recorded_events_survive_the_bag_and_become_requests(tmp_path: Path) -> None:
    """A recording holds the events as any other zagv topic (zagv_msgs/msg/Message); the replay reads them back."""
    log = ServiceEventLog()
    rec = BagRecorder(tmp_path / "bag")
    for i in range(10):
        rec.write("odom", m.Odometry(stamp=i * 0.04), int(i * 0.04e9))
    ev = log.request_received(0.15, m.Empty())
    rec.write(TOPIC, ev, int(0.16e9))
    update = m.LocalizationUpdate(ok=True, pose=m.PoseWithCovariance(stamp=0.2))
    rec.write(TOPIC, log.response_sent(0.22, ev.sequence, update, "scan", 0.2), int(0.23e9))
    rec.close()
    with BagSource(tmp_path / "bag") as src:
        assert src.topics["/" + TOPIC] == "zagv_msgs/msg/Message"
        reqs = recorded_requests(src, src.start_ns, src.end_ns)
        assert not src.problems
    assert reqs == [RecordedRequest("localization/nomotion", 1, codec.encode(m.Empty()), int(0.16e9), "scan", 0.2,
                                    received_stamp_s=0.15)]


def test_a_request_that_names_its_scan_is_issued_again_for_the_scan_it_was_served_on() -> None:
    """An initial pose (or an update at rest) served live on the scan stamped 12.34 s is issued again with that stamp,
    so that the replayed filter is re-initialised (updated) on the same scan; requests without such a field, or not
    served on a scan, as recorded."""
    pose = m.InitialPoseRequest(pose=m.Pose2D(x=1.0, y=2.0, theta=0.5), covariance=[0.01] * 9)
    served = RecordedRequest("localization/initial_pose", 1, codec.encode(pose), 100, "scan", 12.34,
                             received_stamp_s=12.3)
    again = codec.decode_as(m.InitialPoseRequest, replay_payload(served))
    assert (again.at_scan_stamp, again.stamp) == (12.34, 12.3)  # the scans before 12.3 s are ignored, as live
    assert (again.pose, again.covariance) == (pose.pose, pose.covariance)
    unserved = RecordedRequest("localization/initial_pose", 2, codec.encode(pose), 100)
    assert replay_payload(unserved) == unserved.request
    # nav asks for an update at rest with an Empty request: the same bytes as NoMotionRequest's defaults
    nomotion = RecordedRequest("localization/nomotion", 1, codec.encode(m.Empty()), 100, "scan", 12.34)
    assert codec.decode_as(m.NoMotionRequest, replay_payload(nomotion)).at_scan_stamp == 12.34
    global_ = RecordedRequest("localization/global", 1, codec.encode(m.Empty()), 100, "scan", 12.34)
    assert replay_payload(global_) == global_.request  # no scan to name in its type
    garbled = RecordedRequest("localization/initial_pose", 3, b"\xc1", 100, "scan", 12.34)
    assert replay_payload(garbled) == b"\xc1"  # the service refuses it with the reason
