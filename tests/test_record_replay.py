"""Record, replay and the black box on a corridor run, checked with third-party readers (rosbags, mcap).

The in-CI slice drives the first Table 3 goal, then e-stops past 65 s of sim time and at least 62 s after the
stack was ready (so the black box holds a full minute); the whole run (all 7 goals) and
the FR079 replay into SLAM are ``long`` (``tests/test_record_replay_long.py``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from proto import codec
from proto import messages as m
from services.common.se2 import yaw_to_quaternion
from services.launch.bench_record import (
    bag_mb,
    record_corridor,
    replay_into_localization,
    trajectory_rms_m,
    trajectory_rms_per_leg_m,
)

# a stack start, a sim run to 65 s and a replay: minutes on a loaded machine, about one minute on 2 free cores
pytestmark = [pytest.mark.integration, pytest.mark.slow, pytest.mark.timeout(900)]


@pytest.fixture(scope="module")
def corridor(tmp_path_factory: pytest.TempPathFactory):
    return record_corridor(tmp_path_factory.mktemp("corridor"), goals=1, speed=4.0, estop_at_s=65.0)


def _stamp(header) -> float:
    return header.stamp.sec + header.stamp.nanosec * 1e-9


def _is_yaw_quaternion(q, theta: float) -> bool:
    """``q`` is exactly the REP-103 rotation about z by ``theta``: (0, 0, sin θ/2, cos θ/2), every field bit-equal
    (a float64 survives CDR unchanged, so a recorded quaternion is the one computed from the published yaw)."""
    return (q.x, q.y, q.z, q.w) == yaw_to_quaternion(theta)


def _by_stamp(t: type, payloads: list[bytes]) -> dict[int, list]:
    out: dict[int, list] = {}
    for p in payloads:
        msg = codec.decode_as(t, p)
        out.setdefault(round(msg.stamp * 1e9), []).append(msg)
    return out


def _published_at(by_stamp: dict[int, list], t_s: float) -> list:
    """Published messages whose stamp is the bag header's stamp (to the nanosecond of its Time)."""
    return by_stamp.get(round(t_s * 1e9), [])


def check_bag_matches_published(bag: Path, published: dict[str, list[bytes]]) -> dict[str, int]:
    """Every LaserScan, Odometry and TF in ``bag`` decodes (rosbags typestore) and equals a published message.

    Zenoh drops samples of a congested best-effort subscriber, so on a loaded machine the harness can miss a message
    that the recorder got: a message with no published message at its stamp is counted as unseen (at most 1 % of a
    topic); one that has any must equal one of them."""
    scans = _by_stamp(m.LaserScan, published["scan"])
    odoms = _by_stamp(m.Odometry, published["odom"])
    map_odom = _by_stamp(m.Transform2D, published["tf/map_odom"])
    counts = {"/scan": 0, "/odom": 0, "/tf": 0, "/tf_static": 0}
    unseen = dict.fromkeys(counts, 0)
    scan_stamps: list[float] = []
    raw_by_topic: dict[str, list[bytes]] = {k: [] for k in counts}
    with AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
        conns = [c for c in reader.connections if c.topic in counts]
        for conn, _, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, conn.msgtype)
            counts[conn.topic] += 1
            raw_by_topic[conn.topic].append(bytes(raw))
            if conn.topic == "/scan":
                t = _stamp(msg.header)
                scan_stamps.append(t)
                if not _published_at(scans, t):
                    unseen["/scan"] += 1
                    continue
                assert any(
                    msg.header.frame_id == w.frame and np.array_equal(msg.ranges, codec.array(w, "ranges"))
                    and np.array_equal(msg.intensities, codec.array(w, "intensities"))
                    and (msg.angle_min, msg.angle_increment, msg.range_min, msg.range_max) == (
                        np.float32(w.angle_min), np.float32(w.angle_increment), np.float32(w.range_min),
                        np.float32(w.range_max))
                    for w in _published_at(scans, t)), f"scan at {t} s differs from every scan published then"
            elif conn.topic == "/odom":
                t = _stamp(msg.header)
                if not _published_at(odoms, t):
                    unseen["/odom"] += 1
                    continue
                p, v = msg.pose.pose, msg.twist.twist
                assert any(
                    (p.position.x, p.position.y) == (w.pose.x, w.pose.y)
                    and _is_yaw_quaternion(p.orientation, w.pose.theta)
                    and (v.linear.x, v.linear.y, v.angular.z) == (w.twist.vx, w.twist.vy, w.twist.wz)
                    and (msg.header.frame_id, msg.child_frame_id) == (w.frame, w.child_frame)
                    for w in _published_at(odoms, t)), f"odom at {t} s differs from every odom published then"
            else:
                for tf in msg.transforms:
                    t, parent, child = _stamp(tf.header), tf.header.frame_id, tf.child_frame_id
                    tr = tf.transform.translation
                    if (parent, child) == ("map", "odom"):
                        poses = [(w.x, w.y, w.theta) for w in _published_at(map_odom, t)]
                    elif (parent, child) == ("odom", "base_link"):
                        poses = [(w.pose.x, w.pose.y, w.pose.theta) for w in _published_at(odoms, t)]
                    else:
                        assert (parent, child) == ("base_link", "laser") and conn.topic == "/tf_static"
                        poses = [(w.mount.x, w.mount.y, w.mount.theta) for ws in scans.values() for w in ws]
                    if not poses:
                        unseen[conn.topic] += 1
                        continue
                    assert any((tr.x, tr.y, tr.z) == (*pose[:2], 0.0)
                               and _is_yaw_quaternion(tf.transform.rotation, pose[2])
                               for pose in poses), f"{parent}->{child} at {t} s differs from what was published"
    print(f"{bag.name}: {counts} messages, not seen by the harness {unseen}")
    for topic, n in unseen.items():
        assert n <= 0.01 * counts[topic], f"{n} of {counts[topic]} {topic} messages were never seen published"
    # the mcap reader (no ROS) sees the same channels and the same CDR payloads
    with open(next(bag.glob("*.mcap")), "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
        got: dict[str, list[bytes]] = {k: [] for k in counts}
        for _, channel, message in reader.iter_messages(topics=list(counts)):
            got[channel.topic].append(message.data)
    assert got == raw_by_topic
    # nothing lost: every scan published while the recording ran is in it (the first and last stamp may be shared)
    lo, hi = round(min(scan_stamps) * 1e9), round(max(scan_stamps) * 1e9)
    assert counts["/scan"] >= sum(len(v) for k, v in scans.items() if lo < k < hi)
    return counts


def test_recording_decodes_with_rosbags_and_mcap_and_equals_what_was_published(corridor) -> None:
    assert corridor.goals_reached == corridor.goals == 1
    counts = check_bag_matches_published(corridor.bag, corridor.published)
    mb = bag_mb(corridor.bag)
    print(f"recording: {mb:.2f} MB over {corridor.sim_s:.1f} s of robot time ({mb / corridor.sim_s * 60:.2f} MB/min), "
          f"zagv record CPU {corridor.record_cpu_s / corridor.sim_s:.3f} cores at 1x")
    assert counts["/scan"] > 200 and counts["/odom"] > 300 and counts["/tf"] > 500 and counts["/tf_static"] == 1


def test_replay_into_localization_alone_reproduces_the_trajectory(corridor, tmp_path: Path) -> None:
    """The map trajectory (map -> odom composed with odom, at every odom) of localization fed the bag's scans and
    odometry equals the recorded one within 0.01 m RMS over the bag."""
    bag_span = _bag_span_s(corridor.bag)
    odom = [o for o in (codec.decode_as(m.Odometry, p) for p in corridor.published["odom"])
            if bag_span[0] <= o.stamp <= bag_span[1]]
    recorded = [codec.decode_as(m.Transform2D, p) for p in corridor.published["tf/map_odom"]]
    replayed = replay_into_localization(corridor.bag, corridor.world_yaml, tmp_path / "replay", rate=1.0)
    rms_m, compared = trajectory_rms_m(recorded, replayed, odom)
    legs = trajectory_rms_per_leg_m(recorded, replayed, odom, corridor.leg_starts_s)
    print(f"replay into localization: {compared} poses compared of {len(odom)} odom in the bag, RMS {rms_m:.4f} m; "
          f"per leg (at rest, goal 1): {', '.join(f'{r:.4f} m/{n}' for r, n in legs)}")
    assert compared >= 0.9 * len(odom)
    assert rms_m < 0.01


def _bag_span_s(bag: Path) -> tuple[float, float]:
    with AnyReader([bag]) as reader:
        return reader.start_time / 1e9, reader.end_time / 1e9


def test_blackbox_bag_covers_the_minute_before_the_estop(corridor) -> None:
    """The e-stop's black box bag holds the 60 s before it, and each of its scans, odometry and transforms equals a
    message that was published (the harness listened from before the first service started)."""
    bags = [d for d in corridor.blackbox_dir.iterdir() if "estop" in d.name]
    assert len(bags) == 1, list(corridor.blackbox_dir.iterdir())
    with AnyReader(bags, default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
        scan_conns = [c for c in reader.connections if c.topic == "/scan"]
        times = [t / 1e9 for _, t, _ in reader.messages(connections=scan_conns)]
        wheels = [c for c in reader.connections if c.topic == "/wheels"]
        assert wheels and wheels[0].msgtype == "zagv_msgs/msg/Message"
    assert times[0] <= corridor.estop_s - 60.0 and times[-1] >= corridor.estop_s
    published = {codec.decode_as(m.LaserScan, p).stamp for p in corridor.published["scan"]}
    assert sum(1 for t in times if corridor.estop_s - 60 <= t <= corridor.estop_s) >= 0.9 * sum(
        1 for t in published if corridor.estop_s - 60 <= t <= corridor.estop_s)
    check_bag_matches_published(bags[0], corridor.published)
