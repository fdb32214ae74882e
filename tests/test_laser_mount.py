"""The laser mount from a bag's transforms: chains of frames, upside-down scanners, tilted ones refused.

A scanner hung upside down (roll = π in ``/tf_static``) sweeps clockwise seen from above; read as if upright, its
scans come out mirrored and the map with them. The log reader and the replay's ROS decoder must give exactly the
points the same scanner gives upright.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.rosbag1 import Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from services.common.laser_mount import Transform3D, planar_mount, upright_scan
from services.localization.slam.logs import read_log
from services.localization.slam.offline import scan_points
from services.recorder.rosconv import RosDecoder

STORE = get_typestore(Stores.ROS1_NOETIC)
STORE.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))


def _rolled(x_m: float, y_m: float, z_m: float, yaw_rad: float, roll_rad: float) -> Transform3D:
    """A transform rotated by yaw about z after roll about x (R = Rz(yaw)·Rx(roll))."""
    from scipy.spatial.transform import Rotation

    q = Rotation.from_euler("ZX", [yaw_rad, roll_rad]).as_quat()
    return Transform3D((x_m, y_m, z_m), (float(q[0]), float(q[1]), float(q[2]), float(q[3])))


def test_the_mount_is_composed_along_the_chain_of_frames() -> None:
    fixed = {"laser": ("laser_mount", Transform3D.planar(0.1, 0.0, math.pi / 2)),
             "laser_mount": ("base_link", Transform3D.planar(0.12, 0.02, 0.0)),
             "base_link": ("base_footprint", Transform3D.planar(0.5, 0.0, 0.0))}
    np.testing.assert_allclose(planar_mount("laser", fixed, "base_link").pose, [0.22, 0.02, math.pi / 2], atol=1e-12)
    np.testing.assert_allclose(planar_mount("laser", fixed, None).pose, [0.72, 0.02, math.pi / 2], atol=1e-12)
    np.testing.assert_allclose(planar_mount("other", fixed, "base_link").pose, [0.0, 0.0, 0.0])
    assert not planar_mount("laser", fixed, "base_link").upside_down


def test_an_upside_down_scan_gives_the_points_of_the_upright_one() -> None:
    """A wall seen by a laser at (0.3, -0.1) turned 0.4 rad, once upright and once hung upside down: the upside-down
    scanner's beam i looks along -a_i, so it sees the wall at the range the upright one sees along -a_i."""
    angles = -2.0 + np.arange(161) * 0.025
    wall_x_m = 4.0  # the wall x = 4 m in the laser's own (upright) frame

    def ranges_along(headings: np.ndarray) -> np.ndarray:
        with np.errstate(divide="ignore"):
            r = wall_x_m / np.cos(headings)
        return np.where(np.cos(headings) > 0.2, r, np.inf)

    upright = planar_mount("laser", {"laser": ("base_link", _rolled(0.3, -0.1, 0.25, 0.4, 0.0))}, "base_link")
    hung = planar_mount("laser", {"laser": ("base_link", _rolled(0.3, -0.1, 0.25, 0.4, math.pi))}, "base_link")
    assert hung.upside_down and not upright.upside_down
    np.testing.assert_allclose(hung.pose, upright.pose, atol=1e-12)
    hung_ranges = ranges_along(-angles)  # what the upside-down scanner measures, beam by beam
    first, flipped = upright_scan(float(angles[0]), 0.025, hung_ranges)
    flipped_angles = first + np.arange(len(flipped)) * 0.025
    np.testing.assert_allclose(flipped_angles[::-1], -angles, atol=1e-12)
    np.testing.assert_allclose(flipped, ranges_along(flipped_angles))  # each beam now where an upright one looks


def test_a_tilted_laser_is_refused_with_its_frame_named() -> None:
    tilted = {"laser": ("base_link", _rolled(0.2, 0.0, 0.3, 0.0, math.radians(30)))}
    with pytest.raises(ValueError, match=r"'laser' is tilted 30.0 deg"):
        planar_mount("laser", tilted, "base_link")
    slight = {"laser": ("base_link", _rolled(0.2, 0.0, 0.3, 0.0, math.radians(3)))}
    assert not planar_mount("laser", slight, "base_link").upside_down


def test_the_replay_decoder_turns_an_upside_down_scan_upright() -> None:
    types = get_typestore(Stores.ROS2_HUMBLE).types
    tf_msg = types["tf2_msgs/msg/TFMessage"]
    stamped = types["geometry_msgs/msg/TransformStamped"]
    header = types["std_msgs/msg/Header"]
    time_t = types["builtin_interfaces/msg/Time"]
    mount = _rolled(0.2, 0.05, 0.4, 0.1, math.pi)
    q = mount.rotation_xyzw
    tf = stamped(header=header(stamp=time_t(sec=0, nanosec=0), frame_id="base_link"), child_frame_id="laser",
                 transform=types["geometry_msgs/msg/Transform"](
                     translation=types["geometry_msgs/msg/Vector3"](x=0.2, y=0.05, z=0.4),
                     rotation=types["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3])))
    decoder = RosDecoder()
    assert decoder.decode("/tf_static", "tf2_msgs/msg/TFMessage", tf_msg(transforms=[tf])) == []
    ranges = np.array([1.0, 2.0, 3.0, np.inf], np.float32)
    scan = types["sensor_msgs/msg/LaserScan"](
        header=header(stamp=time_t(sec=1, nanosec=0), frame_id="laser"), angle_min=-0.3, angle_max=0.3,
        angle_increment=0.2, time_increment=0.0, scan_time=0.1, range_min=0.05, range_max=30.0, ranges=ranges,
        intensities=np.array([10.0, 20.0, 30.0, 40.0], np.float32))
    [(name, out)] = decoder.decode("/scan", "sensor_msgs/msg/LaserScan", scan)
    assert name == "scan"
    assert out.angle_min == pytest.approx(-0.3) and out.angle_max == pytest.approx(0.3)  # -(a_min + 3·Δa) = -0.3
    np.testing.assert_array_equal(np.frombuffer(out.ranges, "<f4"), ranges[::-1])
    np.testing.assert_array_equal(np.frombuffer(out.intensities, "<f4"), [40.0, 30.0, 20.0, 10.0])
    assert (out.mount.x, out.mount.y, out.mount.theta) == pytest.approx((0.2, 0.05, 0.1))


@pytest.fixture
def csail_bag(shared_dir) -> Path:
    path = shared_dir / "data" / "logs" / "mit-csail.orig.bag"
    if not path.is_file():
        pytest.skip(f"benchmark log not found: {path}")
    return path


def _hang_upside_down(source: Path, target: Path, n_scans: int) -> None:
    """A copy of ``source``'s first ``n_scans`` scans (and the odometry and transforms of that time) as an
    upside-down scanner on the same spot records them: each scan's beams reversed, angles kept, and a
    ``/tf_static`` base -> ``laser_upside_down`` transform with roll π (and a height, which a 2-D scan ignores)."""
    with AnyReader([source]) as reader, Writer(target) as writer:
        scan_conn = next(c for c in reader.connections if c.msgtype == "sensor_msgs/msg/LaserScan")
        odom_conn = next(c for c in reader.connections if c.msgtype == "nav_msgs/msg/Odometry")
        scans = [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages(connections=[scan_conn])]
        scans = scans[:n_scans]
        odom = [(t, reader.deserialize(raw, c.msgtype)) for c, t, raw in reader.messages(connections=[odom_conn])]
        base = next(o.child_frame_id for _, o in odom if o.child_frame_id).lstrip("/") or "base_link"
        flipped_frame = "laser_upside_down"
        mount = _rolled(0.0, 0.0, 0.35, 0.0, math.pi)
        q = mount.rotation_xyzw
        t = STORE.types
        tf = t["geometry_msgs/msg/TransformStamped"](
            header=t["std_msgs/msg/Header"](seq=0, stamp=scans[0].header.stamp, frame_id=base),
            child_frame_id=flipped_frame, transform=t["geometry_msgs/msg/Transform"](
                translation=t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.35),
                rotation=t["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3])))
        static = writer.add_connection("/tf_static", "tf2_msgs/msg/TFMessage", typestore=STORE)
        writer.write(static, 0, STORE.serialize_ros1(t["tf2_msgs/msg/TFMessage"](transforms=[tf]),
                                                     "tf2_msgs/msg/TFMessage"))
        out_scan = writer.add_connection("/scan", "sensor_msgs/msg/LaserScan", typestore=STORE)
        out_odom = writer.add_connection("/odom", "nav_msgs/msg/Odometry", typestore=STORE)
        for k, scan in enumerate(scans):
            hung = dataclasses.replace(scan, header=dataclasses.replace(scan.header, frame_id=flipped_frame),
                                       ranges=np.asarray(scan.ranges)[::-1].copy(),
                                       intensities=np.asarray(scan.intensities)[::-1].copy())
            writer.write(out_scan, k + 1, STORE.serialize_ros1(hung, "sensor_msgs/msg/LaserScan"))
        for stamp_ns, msg in odom:
            writer.write(out_odom, stamp_ns, STORE.serialize_ros1(msg, "nav_msgs/msg/Odometry"))


def test_a_real_log_recorded_upside_down_reads_as_the_original(csail_bag: Path, tmp_path: Path) -> None:
    """MIT CSAIL's first 300 scans re-recorded by the same laser hung upside down (its beams in reverse order, a
    roll-π mount 0.35 m up): every scan gives the original's robot-frame points and the odometry is unchanged, so
    the map is the original's. Read as if upright, the scans would be mirrored."""
    hung_bag = tmp_path / "csail-upside-down.bag"
    _hang_upside_down(csail_bag, hung_bag, 300)
    original, hung = read_log(csail_bag), read_log(hung_bag)
    assert len(hung.scans) == 300
    np.testing.assert_allclose(hung.sensor_pose, original.sensor_pose, atol=1e-12)
    for k in range(300):
        np.testing.assert_allclose(hung.scans[k].odom_pose, original.scans[k].odom_pose, atol=1e-9)
        np.testing.assert_allclose(scan_points(hung, k), scan_points(original, k), atol=1e-5)  # float32 angles
    mirrored = scan_points(original, 150) * np.array([1.0, -1.0])  # what ignoring the roll would have given
    assert np.abs(scan_points(hung, 150) - mirrored).max() > 1.0
