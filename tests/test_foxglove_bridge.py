"""The Foxglove bridge seen by the official npm client ``@foxglove/ws-protocol`` (third-party code), and its core."""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from proto import messages as m
from services.common.ports import free_port
from services.common.robot import RobotSpec
from services.foxglove_bridge import convert
from services.launch.stack_process import Stack

CLIENT_DIR = Path(__file__).parent / "foxglove_client"


@pytest.fixture(scope="module")
def foxglove_client() -> Path:
    """The npm client folder, installed from its lock file when node_modules is missing."""
    if not shutil.which("node") or not shutil.which("npm"):
        pytest.skip("node and npm are needed for the Foxglove client test (apt-get install nodejs npm)")
    if not (CLIENT_DIR / "node_modules").is_dir():
        r = subprocess.run(["npm", "ci", "--no-audit", "--no-fund"], cwd=CLIENT_DIR, capture_output=True, text=True,
                           timeout=300)
        if r.returncode != 0:
            pytest.skip(f"npm ci failed in {CLIENT_DIR} (offline?): {r.stderr[-500:]}")
    return CLIENT_DIR


def test_every_conversion_encodes() -> None:
    """Foxglove messages are opaque SDK objects: each conversion must at least encode (values: the client test)."""
    ranges = np.array([1.0, np.inf, 2.5], "<f4")
    s = m.LaserScan(stamp=12.5, angle_min=-0.1, angle_increment=0.1, ranges=ranges.tobytes(),
                    mount=m.Pose2D(x=0.45, theta=0.1))
    grid = m.OccupancyGrid(width=2, height=2, resolution=0.1, data=bytes([0, 100, 255, 50]))
    path = m.Path(poses=np.zeros((4, 3), "<f4").tobytes())
    out = [convert.laser_scan(s), convert.grid(grid), convert.transforms(s), convert.poses(path),
           convert.transforms(m.Odometry()), convert.transforms(m.Transform2D()),
           convert.robot_scene(RobotSpec(), m.WheelStates(modules=[m.ModuleState(steer_rad=0.3)] * 2), 1.0)]
    assert all(len(x.encode()) > 0 for x in out)
    assert convert.transforms(m.WheelStates()) is None
    assert (convert.timestamp(12.5).sec, convert.timestamp(12.5).nsec) == (12, 500_000_000)


def test_goal_json_from_foxglove() -> None:
    doc = {"header": {"frame_id": "map"}, "pose": {"position": {"x": 1.0, "y": 2.0, "z": 0.0},
                                                   "orientation": {"x": 0, "y": 0, "z": 1.0, "w": 0.0}}}
    x, y, t = convert.goal_from_json(doc)
    assert (x, y) == (1.0, 2.0) and abs(t) == pytest.approx(math.pi)
    with pytest.raises(KeyError):
        convert.goal_from_json({"pose": {}})


@pytest.mark.integration
def test_npm_client_decodes_scan_map_and_tf(tmp_path: Path, foxglove_client: Path) -> None:
    port = free_port()
    t_start = time.monotonic()
    with Stack(tmp_path, ["sim", "lidar", "localization", "foxglove_bridge"],
               extra_args=["--foxglove-port", str(port)]) as stack:
        t0 = time.monotonic()
        r = subprocess.run(["node", "check.mjs", f"ws://127.0.0.1:{port}", "/scan", "/map", "/tf"],
                           cwd=foxglove_client, capture_output=True, text=True, timeout=120)
        assert r.returncode == 0, r.stderr + stack.output()[-3000:]
        print(f"stack ready in {t0 - t_start:.1f} s, client done in {time.monotonic() - t0:.1f} s")
    got = {d["topic"]: d for d in map(json.loads, r.stdout.splitlines())}
    scan, grid, tf = got["/scan"], got["/map"], got["/tf"]
    assert scan["schemaName"] == "foxglove.LaserScan" and scan["encoding"] == "protobuf"
    assert scan["message"]["frame_id"] == "laser" and scan["message"]["ranges"]["length"] > 100
    g = grid["message"]
    assert grid["schemaName"] == "foxglove.Grid" and g["column_count"] == 640 and g["row_stride"] == 640
    assert g["data"]["length"] == 640 * 350 and g["frame_id"] == "map"  # the corridor world's map
    assert tf["schemaName"] == "foxglove.FrameTransforms"
    assert tf["message"]["transforms"][0]["parent_frame_id"] in {"map", "odom", "base_link"}
