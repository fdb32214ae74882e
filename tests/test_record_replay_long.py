"""Long record/replay acceptance runs (``make test-long``): the whole corridor Table 3 run (one repeat) recorded and
replayed into localization alone, and a real robot's ROS 1 bag (FR079) replayed into live SLAM, scored like
``zagv map eval`` against the offline ``zagv map build`` figure."""

from __future__ import annotations

import math
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh

from proto import codec
from proto import messages as m
from services.cli.bench_record import (
    _env,
    bag_mb,
    record_corridor,
    replay_into_localization,
    replay_speed_factor,
    trajectory_rms_m,
)
from services.cli.stack_process import REPO_ROOT, Stack
from services.common.se2 import compose
from tests.test_record_replay import check_bag_matches_published

pytestmark = [pytest.mark.integration, pytest.mark.long, pytest.mark.timeout(3600)]


def test_full_corridor_run_records_and_replays(tmp_path: Path) -> None:
    rec = record_corridor(tmp_path, speed=3.0)
    counts = check_bag_matches_published(rec.bag, rec.published)
    recorded = [codec.decode_as(m.Transform2D, p) for p in rec.published["tf/map_odom"]]
    odom = [codec.decode_as(m.Odometry, p) for p in rec.published["odom"]]
    replayed = replay_into_localization(rec.bag, rec.world_yaml, tmp_path / "replay", rate=1.0)
    rms_m, matched = trajectory_rms_m(recorded, replayed, [o for o in odom if o.stamp >= recorded[0].stamp])
    speed = replay_speed_factor(rec.bag)
    print(f"corridor run: {rec.goals_reached}/{rec.goals} goals, {rec.sim_s:.0f} s, bag {bag_mb(rec.bag):.1f} MB "
          f"({bag_mb(rec.bag) / (rec.sim_s / 60):.1f} MB/min), record CPU {rec.record_cpu_s / rec.sim_s:.3f} cores, "
          f"counts {counts}; replay RMS {rms_m:.4f} m over {matched} poses; replay x{speed:.1f}")
    assert rec.goals_reached == rec.goals == 7
    assert matched > 1000 and rms_m < 0.01


def test_fr079_ros1_bag_replayed_into_live_slam(tmp_path: Path, shared_dir: Path) -> None:
    from services.localization.slam.evaluation import parse_relations, relative_pose_error, scan_poses
    from services.localization.slam.logs import read_log
    from services.localization.slam.offline import run_slam

    bag = shared_dir / "data" / "logs" / "fr079.orig.bag"
    with (shared_dir / "data" / "logs" / "fr079.relations").open() as f:
        relations = parse_relations(f)
    log = read_log(bag)
    offline = run_slam(log)
    stamps, poses = offline.slam.trajectory()
    offline_error = relative_pose_error(stamps, scan_poses(poses, log.sensor_pose), relations)

    config = tmp_path / "mapping.toml"
    config.write_text('[clock]\nuse_sim_time = true\n\n[localization]\nmode = "mapping"\n')
    map_odom: list[m.Transform2D] = []
    maps: list[int] = []
    lock = threading.Lock()
    with Stack(tmp_path, ["localization"], sim=False, extra_args=["--config", str(config)]).start(
            ready_timeout_s=300.0) as stack:
        session = stack.session()

        def on_tf(sample: zenoh.Sample) -> None:
            with lock:
                map_odom.append(codec.decode_as(m.Transform2D, sample.payload.to_bytes()))

        def on_map(sample: zenoh.Sample) -> None:
            with lock:
                maps.append(int((np.frombuffer(codec.decode_as(m.OccupancyGrid, sample.payload.to_bytes()).data,
                                               np.int8) >= 0).sum()))

        subs = [session.declare_subscriber(stack.keys("tf/map_odom"), on_tf),
                session.declare_subscriber(stack.keys("map"), on_map)]
        t0 = time.monotonic()
        subprocess.run([sys.executable, "-m", "services.cli", "replay", str(bag), "scan", "odom", "--rate", "2",
                        "--quiet", "--connect", stack.endpoint], cwd=REPO_ROOT, env=_env(), check=True,
                       stdin=subprocess.DEVNULL, timeout=3600)
        replay_s = time.monotonic() - t0
        time.sleep(2.0)
        for s in subs:
            s.undeclare()
    # the live estimate at each scan: the latest map->odom (stamped with the scan) composed with that scan's odom
    tf_stamps = np.array([t.stamp for t in map_odom])
    tf_poses = np.array([[t.x, t.y, t.theta] for t in map_odom])
    scan_stamps = np.array([s.stamp_s for s in log.scans])
    idx = np.clip(np.searchsorted(tf_stamps, scan_stamps + 1e-6) - 1, 0, len(tf_stamps) - 1)
    robot = compose(tf_poses[idx], np.array([s.odom_pose for s in log.scans]))
    live_error = relative_pose_error(scan_stamps, scan_poses(robot, log.sensor_pose), relations)
    print(f"fr079 live SLAM via replay (x2, {replay_s:.0f} s): map grew to {max(maps) if maps else 0} known cells "
          f"in {len(maps)} maps; RPE {live_error.translation_mean_m:.4f} m / {live_error.rotation_mean_rad:.4f} rad "
          f"vs offline {offline_error.translation_mean_m:.4f} m / {offline_error.rotation_mean_rad:.4f} rad "
          f"({live_error.n_relations} relations)")
    assert len(maps) >= 3 and maps[-1] > maps[0]  # built live
    assert live_error.translation_mean_m <= 1.10 * offline_error.translation_mean_m
    assert math.isfinite(live_error.rotation_mean_rad)
