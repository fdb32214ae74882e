"""hmi_api's I/O-free parts: pose database, password hashes, the jog dead-man, display data."""

from __future__ import annotations

import io
import math
import sqlite3

import msgspec
import numpy as np
import pytest
from PIL import Image

from proto.messages import LaserScan, OccupancyGrid, Odometry, Pose2D, PoseWithCovariance, Transform2D, Twist2D
from services.common.grid import grid_png
from services.hmi_api import auth
from services.hmi_api.jog import JogGate
from services.hmi_api.posedb import SCHEMA_VERSION, PoseDb, PoseDbError, PoseNotFound
from services.hmi_api.view import RobotView, VelocityRecorder


@pytest.fixture
def db(tmp_path):
    d = PoseDb(tmp_path / "poses.sqlite3")
    yield d
    d.close()


def test_posedb_schema_wal_and_full_sync(db):
    assert db.version == SCHEMA_VERSION
    assert db._db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    assert db._db.execute("PRAGMA synchronous").fetchone()[0] == 2  # FULL


def test_posedb_refuses_a_newer_schema(tmp_path):
    path = tmp_path / "p.sqlite3"
    con = sqlite3.connect(path)
    con.execute(f"PRAGMA user_version = {SCHEMA_VERSION + 1}")
    con.close()
    with pytest.raises(PoseDbError, match="newer than this software"):
        PoseDb(path)


def test_posedb_add_update_delete_and_order(db):
    a = db.add("a", 1.0, 2.0, 0.5)
    b = db.add("b", 3.0, 4.0, 7.0)
    c = db.add(" c ", 5.0, 6.0, -1.0)
    assert [p.name for p in db.list()] == ["a", "b", "c"]
    assert b.theta == pytest.approx(7.0 - 2 * math.pi)
    assert [p.index for p in db.list()] == [1, 2, 3]
    assert [p.name for p in db.move(c.id, "up")] == ["a", "c", "b"]
    assert [p.name for p in db.move(a.id, "up")] == ["a", "c", "b"]  # first stays first
    assert [p.name for p in db.move(a.id, "down")] == ["c", "a", "b"]
    assert [p.name for p in db.move(b.id, "down")] == ["c", "a", "b"]  # last stays last
    upd = db.update(a.id, name="A", x=9.0)
    assert (upd.name, upd.x, upd.y) == ("A", 9.0, 2.0)
    db.delete(c.id)
    assert [p.name for p in db.list()] == ["A", "b"]
    with pytest.raises(PoseNotFound):
        db.delete(c.id)
    with pytest.raises(PoseNotFound):
        db.move(c.id, "up")
    with pytest.raises(PoseDbError, match="name"):
        db.add("  ", 0, 0, 0)
    with pytest.raises(PoseDbError, match="x must be a finite"):
        db.add("n", math.nan, 0, 0)
    with pytest.raises(PoseDbError, match="direction"):
        db.move(a.id, "sideways")


def test_posedb_export_import_is_all_or_nothing(db):
    db.add("a", 1.0, 2.0, 0.5)
    doc = db.export()
    assert doc["format"] == "zagv-poses" and doc["poses"] == [{"name": "a", "x": 1.0, "y": 2.0, "theta": 0.5}]
    db.import_poses([("b", 0.0, 0.0, 0.0), ("c", 1.0, 1.0, 1.0)], replace=False)
    assert [p.name for p in db.list()] == ["a", "b", "c"]
    with pytest.raises(PoseDbError, match="pose 1: y must be"):
        db.import_poses([("d", 0.0, 0.0, 0.0), ("e", 0.0, math.inf, 0.0)], replace=True)
    assert [p.name for p in db.list()] == ["a", "b", "c"]  # nothing changed
    db.import_poses([(p["name"], p["x"], p["y"], p["theta"]) for p in doc["poses"]], replace=True)
    assert [p.name for p in db.list()] == ["a"]


def test_posedb_survives_reopen(tmp_path):
    d = PoseDb(tmp_path / "p.sqlite3")
    d.add("kept", 1.0, 2.0, 3.0)
    d.close()
    d = PoseDb(tmp_path / "p.sqlite3")
    assert [p.name for p in d.list()] == ["kept"]
    d.close()


def test_password_hash_and_first_run(tmp_path):
    h = auth.hash_password("correct horse", n=2**10)
    assert auth.verify_password("correct horse", h)
    assert not auth.verify_password("wrong", h)
    with pytest.raises(ValueError, match="scrypt"):
        auth.verify_password("x", "plain-text")
    stored, password = auth.first_run_hash(tmp_path)
    assert password and auth.verify_password(password, stored)
    again, shown = auth.first_run_hash(tmp_path)
    assert (again, shown) == (stored, None)  # printed once only
    assert (tmp_path / auth.FIRST_RUN_FILE).stat().st_mode & 0o077 == 0


def test_token_store():
    tokens = auth.TokenStore(ttl_s=60)
    t = tokens.issue()
    assert tokens.valid(t) and not tokens.valid("nope") and not tokens.valid(None)
    tokens.revoke(t)
    assert not tokens.valid(t)
    assert not auth.TokenStore(ttl_s=-1).valid(auth.TokenStore(ttl_s=-1).issue())


def test_jog_gate_dead_man():
    gate = JogGate(timeout_s=0.3, zero_repeats=2)
    assert gate.next_output(0.0) is None  # silent until someone jogs
    assert gate.command((0.1, 0.0, 0.2), 1.0)
    assert not gate.command((0.1, 0.0, 0.3), 1.1)  # same jog goes on
    assert gate.next_output(1.2) == (0.1, 0.0, 0.3)
    assert gate.next_output(1.4) == (0.1, 0.0, 0.3)
    assert gate.next_output(1.41) == (0.0, 0.0, 0.0)  # 0.31 s without a request
    assert gate.next_output(1.45) == (0.0, 0.0, 0.0)
    assert gate.next_output(1.5) is None
    assert gate.command((0.2, 0.0, 0.0), 2.0)  # a new jog starts
    gate.stop()
    assert gate.next_output(2.01) == (0.0, 0.0, 0.0)


def test_view_map_pose_scan_and_nan_free_status():
    v = RobotView()
    assert v.robot_pose() is None and v.status(0.0, "wall", {})["pose"] is None
    v.odom = Odometry(pose=Pose2D(x=1.0, y=0.0, theta=math.pi / 2), twist=Twist2D(vx=math.nan))
    assert v.robot_pose()[1] == "odom"
    v.map_odom = Transform2D(x=10.0, y=0.0, theta=0.0)
    (x, y, th), frame = v.robot_pose()
    assert frame == "map" and (x, y, th) == pytest.approx((11.0, 0.0, math.pi / 2))
    ranges = np.array([1.0, np.inf, 2.0, np.nan], dtype="<f4")
    v.scan = LaserScan(angle_min=0.0, angle_increment=math.pi / 2, range_min=0.05, range_max=20.0,
                       ranges=ranges.tobytes(), mount=Pose2D(x=0.5))
    pts = v.scan_points(100)
    # beam 0 along the robot's heading (+y in map): laser at (11, 0.5), hit 1 m further; beam 2 points backwards
    assert pts == pytest.approx([11.0, 1.5, 11.0, -1.5])
    v.pose = PoseWithCovariance(covariance=[0.01, 0, 0, 0, 0.01, 0, 0, 0, math.nan])
    status = v.status(5.0, "sim", {"active": False})
    assert status["odom"]["vx"] is None and status["pose"]["std_theta_rad"] is None
    assert status["stale"] == []
    v.received = {"odom": 10.0, "wheels": 12.5, "pose": 1.0}  # pose pauses while the robot stands still
    assert v.stale(13.0) == ["odom"]
    encoded = msgspec.json.encode(status)
    assert b"NaN" not in encoded and b"Infinity" not in encoded


def test_grid_png_is_north_up():
    # 2 x 3 grid: row 0 (south) free, row 1 (north) occupied except one unknown cell
    grid = OccupancyGrid(width=3, height=2, data=np.array([0, 0, 0, 100, 100, -1], dtype="<i1").tobytes())
    img = np.array(Image.open(io.BytesIO(grid_png(grid))))
    assert img.shape == (2, 3)
    assert img[0].tolist() == [0, 0, 205] and img[1].tolist() == [254, 254, 254]
    with pytest.raises(ValueError):
        grid_png(OccupancyGrid(width=4, height=2, data=b"\x00"))


def test_velocity_recorder_csv():
    rec = VelocityRecorder(history_s=1.0, rate_hz=10.0, cmd_hold_s=0.5)
    odom = Odometry(twist=Twist2D(vx=0.1, vy=0.0, wz=0.2))
    for i in range(30):
        rec.sample(i * 0.1, Twist2D(vx=0.2), 0.0, odom if i else None)
    assert len(rec.rows) == 11  # 1 s at 10 Hz, the oldest dropped
    assert rec.rows[-1][1] == 0.0  # the command is older than 0.5 s: counted as zero
    text = rec.csv().splitlines()
    assert text[0].startswith("t_s,cmd_vx_mps") and len(text) == 12
    assert len(rec.window(0.35)) == 4
