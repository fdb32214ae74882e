"""Log readers on the benchmark logs (CARMEN .clf and ROS 1 .bag) and the offline ``map build`` / ``map eval``."""

from __future__ import annotations

import contextlib
import json

import numpy as np
import pytest

from services.localization.slam.__main__ import main as slam_main
from services.localization.slam.evaluation import parse_relations
from services.localization.slam.logs import read_log


@pytest.fixture
def logs_dir(shared_dir):
    path = shared_dir / "data" / "logs"
    if not (path / "fr079.orig.bag").is_file():
        pytest.skip(f"benchmark logs not found in {path}")
    return path


def test_read_fr079_bag(logs_dir):
    log = read_log(logs_dir / "fr079.orig.bag")
    assert len(log.scans) == 4934
    np.testing.assert_allclose(log.sensor_pose, [0.04, 0.0, 0.0])
    stamps = np.array([s.stamp_s for s in log.scans])
    assert np.all(np.diff(stamps) > 0)
    assert 1000 < log.duration_s < 1100
    first = log.scans[0]
    assert len(first.ranges_m) == len(first.angles_rad) == 360
    assert first.angles_rad[0] == pytest.approx(-np.pi / 2, abs=1e-6)
    assert np.all(np.isfinite([s.odom_pose for s in log.scans]))
    with (logs_dir / "fr079.relations").open() as f:
        relations = parse_relations(f)
    for at in (relations.stamp_from_s, relations.stamp_to_s):
        nearest = np.abs(stamps[np.clip(np.searchsorted(stamps, at), 0, len(stamps) - 1)] - at)
        assert nearest.max() < 1e-4  # every relation names a scan of the bag


def test_carmen_log_and_bag_hold_the_same_scans(logs_dir):
    clf = read_log(logs_dir / "mit-csail.clf")
    bag = read_log(logs_dir / "mit-csail.orig.bag")
    assert len(clf.scans) == len(bag.scans) == 1988
    for k in (0, 700, 1987):
        a, b = clf.scans[k], bag.scans[k]
        assert a.stamp_s == pytest.approx(b.stamp_s, abs=1e-5)
        np.testing.assert_allclose(a.ranges_m, b.ranges_m, atol=1e-4)
        np.testing.assert_allclose(a.angles_rad, b.angles_rad, atol=1e-6)
        np.testing.assert_allclose(a.odom_pose, b.odom_pose, atol=1e-4)


def test_read_log_rejects_unknown_formats(tmp_path):
    path = tmp_path / "scans.txt"
    path.write_text("hello")
    with pytest.raises(ValueError, match="unsupported log format"):
        read_log(path)
    with pytest.raises(FileNotFoundError):
        read_log(tmp_path / "absent.bag")


def test_map_build_and_eval_commands(logs_dir, tmp_path, capsys):
    log = str(logs_dir / "mit-csail.clf")
    relations = str(logs_dir / "mit-csail.relations")
    assert slam_main(["build", log, "--out", str(tmp_path), "--max-scans", "120"]) == 0
    yaml_text = (tmp_path / "map.yaml").read_text()
    assert "image: map.pgm" in yaml_text and "mode: trinary" in yaml_text
    pgm = (tmp_path / "map.pgm").read_bytes()
    assert pgm.startswith(b"P5\n")
    width, height = (int(v) for v in pgm.split(b"\n")[2].split())
    pixels = np.frombuffer(pgm[-width * height:], np.uint8)
    assert set(np.unique(pixels)) <= {0, 205, 254}
    assert (pixels == 0).sum() > 200 and (pixels == 254).sum() > 5000
    trajectory = tmp_path / "map.trajectory.txt"
    assert len(np.loadtxt(trajectory, ndmin=2)) == 120
    out = tmp_path / "err.json"
    assert slam_main(["eval", log, relations, "--trajectory", str(trajectory), "--json", str(out)]) == 0
    figures = json.loads(out.read_text())
    assert figures["n_relations"] > 20 and figures["n_missing"] > 0  # only the first scans were mapped
    assert 0 <= figures["translation_mean_m"] < 0.1
    assert "translational error" in capsys.readouterr().out


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_a_ros2_bag_reads_as_the_ros1_bag_it_was_converted_from(logs_dir, tmp_path, storage):
    """MIT CSAIL's first 200 scans and their odometry written as a ROS 2 bag (MCAP, and sqlite3 without message
    definitions, as ROS 2 before Iron writes it): ``read_log`` takes its folder or its storage file and gives the
    ROS 1 bag's scans."""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    t = store.types
    source = logs_dir / "mit-csail.orig.bag"
    folder = tmp_path / f"csail-{storage}"
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with AnyReader([source]) as reader, Writer(folder, version=8, storage_plugin=plugin) as writer:
        scan_conn = next(c for c in reader.connections if c.msgtype == "sensor_msgs/msg/LaserScan")
        odom_conn = next(c for c in reader.connections if c.msgtype == "nav_msgs/msg/Odometry")
        out = {c.id: writer.add_connection("/" + c.topic.strip("/"), c.msgtype, typestore=store)
               for c in (scan_conn, odom_conn)}
        scans = 0
        for conn, stamp_ns, raw in reader.messages(connections=[scan_conn, odom_conn]):
            if conn is scan_conn:
                if scans == 200:
                    continue
                scans += 1
            msg = reader.deserialize(raw, conn.msgtype)
            header = t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](
                sec=msg.header.stamp.sec, nanosec=msg.header.stamp.nanosec), frame_id=msg.header.frame_id)
            if conn is scan_conn:
                fields = {k: getattr(msg, k) for k in ("angle_min", "angle_max", "angle_increment", "time_increment",
                                                       "scan_time", "range_min", "range_max", "ranges", "intensities")}
                ros2 = t["sensor_msgs/msg/LaserScan"](header=header, **fields)
            else:
                ros2 = t["nav_msgs/msg/Odometry"](header=header, child_frame_id=msg.child_frame_id,
                                                  pose=msg.pose, twist=msg.twist)
            writer.write(out[conn.id], stamp_ns, store.serialize_cdr(ros2, conn.msgtype))
    files = [p for p in folder.iterdir() if p.suffix in (".mcap", ".db3")]
    if storage == "sqlite3":  # as ROS 2 before Iron writes it: no message definitions in the bag
        import sqlite3

        with contextlib.closing(sqlite3.connect(files[0])) as db, db:
            db.execute("DELETE FROM message_definitions")
    original = read_log(source)
    for path in (folder, files[0]):
        converted = read_log(path)
        assert len(converted.scans) == 200
        np.testing.assert_allclose(converted.sensor_pose, original.sensor_pose)
        for a, b in zip(original.scans[:200], converted.scans, strict=True):
            assert b.stamp_s == pytest.approx(a.stamp_s, abs=1e-9)
            np.testing.assert_allclose(b.odom_pose, a.odom_pose, atol=1e-9)
            np.testing.assert_array_equal(b.ranges_m, a.ranges_m)
    (folder / "metadata.yaml").unlink()
    with pytest.raises(ValueError, match="metadata.yaml"):
        read_log(files[0])
