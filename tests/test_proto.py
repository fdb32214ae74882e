"""Wire protocol: every type round-trips, bad payloads raise one clear error, schema files match the Structs."""

from __future__ import annotations

import numpy as np
import pytest

from proto import Keys, ProtoDecodeError, codec, decode, encode
from proto import messages as m
from proto.keys import split_key
from proto.registry import QUERIES, TOPICS, all_types
from proto.schema import drift

P = m.Pose2D(x=1.5, y=-2.0, theta=0.5)
EXAMPLES: dict[type, m.Message] = {
    m.Reply: m.Reply(ok=False, message="no"),
    m.GoalRequest: m.GoalRequest(pose=P, id="g1"),
    m.GoalReply: m.GoalReply(accepted=True, goal_id="g1"),
    m.Waypoint: m.Waypoint(pose=P),
    m.WaypointsRequest: m.WaypointsRequest(waypoints=[m.Waypoint(pose=P, id="a")]),
    m.WaypointsControl: m.WaypointsControl(action="pause"),
    m.InitialPoseRequest: m.InitialPoseRequest(pose=P),
    m.SaveMapRequest: m.SaveMapRequest(name="corridor"),
    m.ModeRequest: m.ModeRequest(mode="mapping"),
    m.ObstacleRequest: m.ObstacleRequest(action="add", rect=[0, 0, 1, 1]),
    m.ObstacleReply: m.ObstacleReply(ok=True, ids=["a"]),
    m.TeleportRequest: m.TeleportRequest(pose=P),
    m.LocalizationUpdate: m.LocalizationUpdate(ok=True, message="updated", pose=m.PoseWithCovariance(pose=P),
                                               map_odom=m.Transform2D(x=0.1, theta=0.02)),
    m.ServiceEvent: m.ServiceEvent(stamp=12.5, event="response_sent", sequence=3, response=b"\x81",
                                   input_topic="scan", input_stamp=12.4),
}


@pytest.mark.parametrize("t", all_types(), ids=lambda t: t.__name__)
def test_every_type_round_trips(t):
    msg = EXAMPLES[t] if t in EXAMPLES else t()
    assert codec.decode_as(t, encode(msg)) == msg


def test_topics_decode_by_key_and_arrays_are_zero_copy():
    ranges = np.array([1.0, np.inf, 2.5], dtype="<f4")
    payload = encode(m.LaserScan(ranges=ranges.tobytes(), range_max=20.0))
    scan = decode("agv/r1/scan", payload)
    view = codec.array(scan, "ranges")
    assert view.base is not None and view.dtype == np.float32
    np.testing.assert_array_equal(view, ranges)
    assert codec.to_display(scan)["ranges"] == [1.0, None, 2.5]


def test_path_rows_have_three_columns():
    poses = np.arange(12, dtype="<f4").reshape(4, 3)
    path = decode("nav/path", encode(m.Path(poses=poses.tobytes())))
    assert codec.array(path, "poses").shape == (4, 3)


@pytest.mark.parametrize("payload", [b"", b"\xc1", b"garbage", encode(m.Odometry()), encode(m.Twist2D(vx=1))[:-3]])
def test_bad_payload_raises_one_clear_error(payload):
    with pytest.raises(ProtoDecodeError) as info:
        decode("cmd_vel", payload)
    assert "cmd_vel" in str(info.value) and "Twist2D" in str(info.value)


def test_wrong_field_type_is_named():
    import msgspec

    payload = msgspec.msgpack.encode({"vx": "fast"})
    with pytest.raises(ProtoDecodeError, match=r"vx"):
        decode("cmd_vel", payload)


def test_queries_have_request_and_reply_types():
    for name, (req, rep) in QUERIES.items():
        assert issubclass(req, m.Message) and issubclass(rep, m.Message), name
    assert codec.query_types("agv/r1/nav/goal") == (m.GoalRequest, m.GoalReply)


def test_keys():
    k = Keys("r7")
    assert k("scan") == "agv/r7/scan"
    assert k.health("drive") == "agv/r7/@health/drive"
    assert split_key("agv/r7/nav/path") == ("r7", "nav/path")
    with pytest.raises(ValueError):
        Keys("a/b")
    with pytest.raises(ValueError):
        split_key("other/x")
    assert set(TOPICS) >= {"cmd_vel", "odom", "scan", "map", "pose", "tf/map_odom", "clock"}


def test_schema_files_match_structs():
    stale = drift()
    assert not stale, f"proto/schema is out of date for {stale}; run `python -m proto.schema`"
