"""Recorder core: zagv messages written as rosbag2/MCAP and read back by third-party readers (rosbags, mcap)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from proto import codec
from proto import messages as m
from services.common.se2 import quaternion_to_yaw
from services.recorder.bag import BagRecorder
from services.recorder.blackbox import RingBuffer, Triggers, save
from services.recorder.source import BagSource


def _scan(i: int) -> m.LaserScan:
    rng = np.random.default_rng(i)
    ranges = rng.uniform(0.1, 20.0, 541).astype("<f4")
    ranges[3] = np.inf
    return m.LaserScan(stamp=i * 0.04, angle_min=-2.356, angle_max=2.356, angle_increment=0.00872, scan_time=0.04,
                       range_min=0.05, range_max=20.0, ranges=ranges.tobytes(),
                       intensities=rng.uniform(0, 200, 541).astype("<f4").tobytes(),
                       mount=m.Pose2D(x=0.31, y=-0.02, theta=0.01), scan_counter=i)


def _odom(i: int) -> m.Odometry:
    return m.Odometry(stamp=i * 0.02, pose=m.Pose2D(x=0.01 * i, y=-0.003 * i, theta=math.sin(i / 10)),
                      twist=m.Twist2D(vx=0.2, vy=-0.05, wz=0.3), pose_covariance=[float(k) for k in range(9)])


def _record(path: Path, **kw) -> BagRecorder:
    rec = BagRecorder(path, **kw)
    for i in range(100):
        t = int(i * 0.04e9)
        rec.write("odom", _odom(i), t)
        rec.write("scan", _scan(i), t)
        rec.write("tf/map_odom", m.Transform2D(stamp=i * 0.04, x=1.5, y=-0.5, theta=0.2), t)
        rec.write("wheels", m.WheelStates(stamp=i * 0.04, modules=[m.ModuleState(steer_rad=0.1 * i)],
                                          fault="" if i < 50 else "overcurrent"), t)
    rec.write("map", m.OccupancyGrid(width=3, height=2, resolution=0.05, origin=m.Pose2D(x=-1.0, y=-2.0),
                                     data=bytes([0, 100, 255, 0, 50, 255])), int(4e9))
    rec.write("nav/path", m.Path(poses=np.array([[0, 0, 0], [1, 2, 0.5]], "<f4").tobytes()), int(4e9))
    rec.close()
    return rec


def test_rosbags_reader_decodes_every_field(tmp_path: Path) -> None:
    bag = tmp_path / "rec"
    _record(bag)
    assert (bag / "metadata.yaml").is_file() and len(list(bag.glob("*.mcap"))) == 1
    store = get_typestore(Stores.ROS2_HUMBLE)
    scans, odoms, tfs, statics = [], [], [], []
    with AnyReader([bag], default_typestore=store) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        assert types["/scan"] == "sensor_msgs/msg/LaserScan" and types["/odom"] == "nav_msgs/msg/Odometry"
        assert types["/tf"] == types["/tf_static"] == "tf2_msgs/msg/TFMessage"
        assert types["/map"] == "nav_msgs/msg/OccupancyGrid" and types["/nav/path"] == "nav_msgs/msg/Path"
        for conn, _, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            {"/scan": scans, "/odom": odoms, "/tf": tfs, "/tf_static": statics}.get(conn.topic, []).append(msg)
    assert len(scans) == 100 and len(odoms) == 100 and len(tfs) == 200 and len(statics) == 1
    for i, s in enumerate(scans):
        want = _scan(i)
        assert s.header.frame_id == "laser" and s.header.stamp.sec * 1e9 + s.header.stamp.nanosec == round(i * 0.04e9)
        assert np.array_equal(s.ranges, codec.array(want, "ranges"))
        assert np.array_equal(s.intensities, codec.array(want, "intensities"))
        assert (s.angle_min, s.range_max) == (np.float32(want.angle_min), np.float32(want.range_max))
    for i, o in enumerate(odoms):
        want = _odom(i)
        p = o.pose.pose
        assert (o.header.frame_id, o.child_frame_id) == ("odom", "base_link")
        assert (p.position.x, p.position.y) == (want.pose.x, want.pose.y)
        assert quaternion_to_yaw(p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w) == pytest.approx(
            want.pose.theta, abs=1e-12)
        assert (o.twist.twist.linear.x, o.twist.twist.linear.y, o.twist.twist.angular.z) == (0.2, -0.05, 0.3)
        assert o.pose.covariance[0 * 6 + 1] == 1.0 and o.pose.covariance[5 * 6 + 5] == 8.0
    frames = {(t.transforms[0].header.frame_id, t.transforms[0].child_frame_id) for t in tfs}
    assert frames == {("odom", "base_link"), ("map", "odom")}
    st = statics[0].transforms[0]
    assert (st.header.frame_id, st.child_frame_id, st.transform.translation.x) == ("base_link", "laser", 0.31)


def test_mcap_reader_sees_ros2_schemas(tmp_path: Path) -> None:
    bag = tmp_path / "rec"
    _record(bag)
    with open(next(bag.glob("*.mcap")), "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
        assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}
        counts = {summary.channels[k].topic: v for k, v in summary.statistics.channel_message_counts.items()}
        assert counts["/scan"] == 100 and counts["/odom"] == 100 and counts["/wheels"] == 100
        n = sum(1 for _ in reader.iter_messages(topics=["/scan"]))
    assert n == 100


def test_zagv_messages_round_trip_exactly(tmp_path: Path) -> None:
    bag = tmp_path / "rec"
    _record(bag)
    got: dict[str, list] = {}
    with BagSource(bag) as src:
        for _, name, msg in src.messages():
            got.setdefault(name, []).append(msg)
        assert not src.problems
    assert got["wheels"] == [m.WheelStates(stamp=i * 0.04, modules=[m.ModuleState(steer_rad=0.1 * i)],
                                           fault="" if i < 50 else "overcurrent") for i in range(100)]
    scan = got["scan"][7]
    want = _scan(7)
    assert scan.ranges == want.ranges and scan.mount == m.Pose2D(x=0.31, y=-0.02, theta=pytest.approx(0.01))
    assert [o.pose.x for o in got["odom"]] == [_odom(i).pose.x for i in range(100)]
    assert got["tf/map_odom"][0].x == 1.5 and got["map"][0].data == bytes([0, 100, 255, 0, 50, 255])
    assert codec.array(got["nav/path"][0], "poses").tolist() == [[0, 0, 0], [1, 2, 0.5]]


def test_split_by_duration_gives_bags_that_open_alone(tmp_path: Path) -> None:
    rec = _record(tmp_path / "rec", split_duration_s=1.0)
    assert len(rec.stats.bags) == 5
    total = 0
    for bag in rec.stats.bags:
        with AnyReader([bag]) as reader:
            assert "/tf_static" in {c.topic for c in reader.connections}  # each bag has the laser mount
            total += sum(c.msgcount for c in reader.connections if c.topic == "/scan")
    assert total == 100
    with BagSource(tmp_path / "rec") as src:  # the split recording replays as one
        assert sum(1 for _, n, _ in src.messages() if n == "scan") == 100


def test_split_by_size(tmp_path: Path) -> None:
    rec = _record(tmp_path / "rec", split_bytes=100_000)
    assert len(rec.stats.bags) > 3
    assert "MB" in rec.stats.line() and "msgs" in rec.stats.line()


def test_unknown_and_malformed_topics_are_reported_and_skipped(tmp_path: Path) -> None:
    store = get_typestore(Stores.ROS2_HUMBLE)
    bag = tmp_path / "foreign"
    with Writer(bag, version=8, storage_plugin=StoragePlugin.SQLITE3) as w:
        odom = w.add_connection("/odom", "nav_msgs/msg/Odometry", typestore=store)
        temp = w.add_connection("/temperature", "sensor_msgs/msg/Temperature", typestore=store)
        broken = w.add_connection("/scan", "sensor_msgs/msg/LaserScan", typestore=store)
        t = store.types
        hdr = t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](sec=1, nanosec=0), frame_id="odom")
        w.write(temp, 1, store.serialize_cdr(t["sensor_msgs/msg/Temperature"](header=hdr, temperature=20.0,
                                                                              variance=0.0),
                                             "sensor_msgs/msg/Temperature"))
        w.write(broken, 2, b"\x00\x01\x00\x00\x05")
        from services.recorder.rosconv import RosEncoder, make_typestore

        enc = RosEncoder(make_typestore())
        (_, _, ros_odom), _ = enc.encode("odom", _odom(3))
        w.write(odom, 3, store.serialize_cdr(ros_odom, "nav_msgs/msg/Odometry"))
    with BagSource(bag) as src:
        got = list(src.messages())
        assert [n for _, n, _ in got] == ["odom"] and got[0][2].pose.x == _odom(3).pose.x
        assert "sensor_msgs/msg/Temperature" in src.problems["/temperature"]
        assert "malformed" in src.problems["/scan"] and src.skipped["/scan"] == 1


def test_ring_buffer_keeps_the_window_and_latched_topics(tmp_path: Path) -> None:
    ring = RingBuffer(window_s=10.0)
    ring.add("map", codec.encode(m.OccupancyGrid(width=1, height=1, data=b"\x00")), 0)
    for i in range(300):  # 30 s of odom at 10 Hz
        ring.add("odom", codec.encode(_odom(i)), int(i * 0.1e9))
    items = ring.snapshot()
    odom_t = [t for t, n, _ in items if n == "odom"]
    assert odom_t[0] == int(19.9e9) and odom_t[-1] == int(29.9e9)
    assert items[0][1] == "map" and items[0][0] == odom_t[0]
    out, count = save(items, tmp_path / "bb", "r1")
    assert count == len(items)
    with AnyReader([out]) as reader:
        assert {c.topic for c in reader.connections} >= {"/map", "/odom", "/tf"}


def test_triggers_fire_on_edges() -> None:
    tr = Triggers()
    assert tr.on_wheels(m.WheelStates(estopped=False)) is None
    assert tr.on_wheels(m.WheelStates(estopped=True)) == "estop"
    assert tr.on_wheels(m.WheelStates(estopped=True)) is None
    assert tr.on_wheels(m.WheelStates(estopped=True, fault="link down")) == "drive-fault"
    assert tr.on_nav_status(m.NavStatus(state="failed", goal_id="g1")) == "goal-failed"
    assert tr.on_nav_status(m.NavStatus(state="failed", goal_id="g1")) is None
    assert tr.on_nav_status(m.NavStatus(state="driving", goal_id="g2")) is None
    assert tr.on_nav_status(m.NavStatus(state="failed", goal_id="g2")) == "goal-failed"


class _FakeMonotonic:
    def __init__(self) -> None:
        self.now_s = 100.0

    def __call__(self) -> float:
        return self.now_s


def test_record_time_base_waits_from_the_subscriptions(monkeypatch: pytest.MonkeyPatch) -> None:
    """A slow session start does not count against the wait for the first clock; without a clock, wall time."""
    from services.recorder import record

    fake = _FakeMonotonic()
    monkeypatch.setattr(record.time, "monotonic", fake)
    clock = record.LogClock()
    fake.now_s += 10.0  # opening the session took 10 s
    assert clock.log_ns(None, 5) is None  # not subscribed yet: undecided
    clock.subscribed()
    fake.now_s += 0.5
    clock.on_clock(m.Clock(stamp=42.0))
    assert clock.sim_base and clock.log_ns(*clock.arrival()) == 42_000_000_000
    no_clock = record.LogClock()
    no_clock.subscribed()
    fake.now_s += record.LogClock.WAIT_S
    assert no_clock.log_ns(None, 7) == 7 and no_clock.sim_base is False


def test_the_record_backlog_holds_samples_in_order_and_counts_what_does_not_fit() -> None:
    """``zagv record``'s queue between the receiving thread and the writer: bounded by payload bytes; a sample past
    the bound is dropped and counted per topic, and the count is reported."""
    import queue

    from services.recorder.record import Backlog

    backlog = Backlog(max_bytes=10)
    assert backlog.put(("agv/r1/scan", b"123456", 1, 2)) and backlog.put(("agv/r1/odom", b"1234", 3, 4))
    assert not backlog.put(("agv/r1/scan", b"1", 5, 6)) and backlog.drop_line().startswith("dropped 1 message(s)")
    assert backlog.get(0.1) == ("agv/r1/scan", b"123456", 1, 2)  # oldest first, and its bytes are free again
    assert backlog.put(("agv/r1/scan", b"12345", 7, 8))
    assert [backlog.get()[3] for _ in range(2)] == [4, 8] and backlog.held_bytes == 0
    with pytest.raises(queue.Empty):
        backlog.get()
    assert backlog.dropped == {"scan": 1} and "(1 scan)" in backlog.drop_line() and Backlog().drop_line() == ""
