"""hmi_api benchmarks: the per-frame work of the WebSocket stream, map encoding, pose commits, login hashing."""

from __future__ import annotations

import math
import tempfile

import msgspec
import numpy as np

from proto.messages import (
    LaserScan,
    ModuleState,
    NavStatus,
    OccupancyGrid,
    Odometry,
    Path,
    Pose2D,
    PoseArray,
    PoseWithCovariance,
    Transform2D,
    WheelStates,
)
from services.common.bench import BenchRow, time_calls
from services.common.grid import grid_png
from services.hmi_api import auth
from services.hmi_api.posedb import PoseDb
from services.hmi_api.view import RobotView


def _view() -> RobotView:
    """A view holding messages of realistic size: 541-beam scan, 5000 particles, 300-pose path, corridor map."""
    rng = np.random.default_rng(0)
    v = RobotView()
    v.odom = Odometry(pose=Pose2D(x=3.0, y=1.0, theta=0.5))
    v.map_odom = Transform2D(x=0.1, y=-0.05, theta=0.01)
    v.pose = PoseWithCovariance(pose=Pose2D(x=3.1, y=0.95, theta=0.51), covariance=[0.01, 0, 0, 0, 0.01, 0, 0, 0, 0.01])
    v.wheels = WheelStates(modules=[ModuleState(steer_rad=0.2, speed_mps=0.1), ModuleState(steer_rad=-0.1)])
    v.nav = NavStatus(state="driving", goal=Pose2D(x=10.0, y=3.0))
    v.scan = LaserScan(angle_min=-2.356, angle_max=2.356, angle_increment=math.radians(0.5), range_min=0.05,
                       range_max=20.0, ranges=rng.uniform(0.5, 15.0, 541).astype("<f4").tobytes())
    v.particles = PoseArray(poses=rng.normal(0, 0.1, (5000, 3)).astype("<f4").tobytes())
    v.path = Path(poses=rng.normal(0, 1, (300, 3)).astype("<f4").tobytes())
    v.local_plan = Path(poses=rng.normal(0, 1, (40, 3)).astype("<f4").tobytes())
    cells = np.zeros((350, 640), dtype=np.int8)
    cells[::7, :] = 100
    cells[:, ::11] = -1
    v.grid = OccupancyGrid(width=640, height=350, data=cells.tobytes())
    return v


def bench_frames() -> list[BenchRow]:
    v = _view()

    def frame() -> bytes:
        return msgspec.json.encode({"status": v.status(0.0, "wall", {}), "scan": v.scan_points(720),
                                    "paths": {"global": v.path_list(v.path), "local": v.path_list(v.local_plan)},
                                    "particles": v.particle_list(1000)})

    t_status = time_calls(lambda: msgspec.json.encode(v.status(0.0, "wall", {})), repeat=500)
    t_frame = time_calls(frame, repeat=200)
    size = len(frame())
    grid = v.grid
    assert grid is not None
    t_png = time_calls(lambda: grid_png(grid), repeat=20, warmup=2)
    return [
        BenchRow("hmi.status_json_us", float(np.median(t_status) * 1e6), "us", "< 500 us (15 Hz per client)"),
        BenchRow("hmi.ws_full_frame_ms", float(np.median(t_frame) * 1e3), "ms",
                 "< 5 ms: scan 541 beams, 1000 of 5000 particles, paths"),
        BenchRow("hmi.ws_full_frame_kb", size / 1024, "KiB", "< 64 KiB"),
        BenchRow("hmi.map_png_640x350_ms", float(np.median(t_png) * 1e3), "ms", "once per map version"),
    ]


def bench_posedb() -> list[BenchRow]:
    with tempfile.TemporaryDirectory() as d:
        db = PoseDb(f"{d}/poses.sqlite3")
        n = iter(range(10**6))
        t_add = time_calls(lambda: db.add(f"p{next(n)}", 1.0, 2.0, 0.3), repeat=100, warmup=5)
        ids = [p.id for p in db.list()]
        t_move = time_calls(lambda: db.move(ids[50], "up"), repeat=50, warmup=2)
        db.close()
    t_hash = time_calls(lambda: auth.verify_password("x", auth.hash_password("x")), repeat=5, warmup=1)
    return [
        BenchRow("hmi.pose_add_commit_ms", float(np.median(t_add) * 1e3), "ms", "WAL + synchronous=FULL (fsync)"),
        BenchRow("hmi.pose_add_commit_p99_ms", float(np.percentile(t_add, 99) * 1e3), "ms", ""),
        BenchRow("hmi.pose_move_105_ms", float(np.median(t_move) * 1e3), "ms", "renumbers the list"),
        BenchRow("hmi.login_scrypt_ms", float(np.median(t_hash) * 1e3 / 2), "ms", "scrypt n=2^14 r=8 (one hash)"),
    ]


BENCHES = [("hmi.frames", bench_frames), ("hmi.posedb", bench_posedb)]
