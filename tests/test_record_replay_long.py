"""Long record/replay acceptance runs (``make test-long``): the whole corridor Table 3 run (one repeat) recorded and
replayed into localization alone, and a real robot's ROS 1 bag (FR079) replayed into live SLAM, scored like
``zagv map eval`` against the offline ``zagv map build`` figure."""

from __future__ import annotations

import asyncio
import json
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
from services.common.node import query
from services.common.se2 import compose
from services.launch.bench_record import (
    _env,
    bag_mb,
    record_corridor,
    replay_into_localization,
    replay_speed_factor,
    trajectory_rms_m,
    trajectory_rms_per_leg_m,
)
from services.launch.stack_process import REPO_ROOT, Stack
from tests.support.waiting import wait_for_sync
from tests.test_record_replay import check_bag_matches_published

pytestmark = [pytest.mark.integration, pytest.mark.long, pytest.mark.timeout(3600)]


def test_full_corridor_run_records_and_replays(tmp_path: Path) -> None:
    rec = record_corridor(tmp_path, speed=3.0)
    counts = check_bag_matches_published(rec.bag, rec.published)
    recorded = [codec.decode_as(m.Transform2D, p) for p in rec.published["tf/map_odom"]]
    odom = [codec.decode_as(m.Odometry, p) for p in rec.published["odom"]]
    replayed = replay_into_localization(rec.bag, rec.world_yaml, tmp_path / "replay", rate=1.0)
    in_bag = [o for o in odom if o.stamp >= recorded[0].stamp]
    rms_m, matched = trajectory_rms_m(recorded, replayed, in_bag)
    legs = trajectory_rms_per_leg_m(recorded, replayed, in_bag, rec.leg_starts_s)
    print("replay RMS per leg (at rest, then goals 1..7): "
          + ", ".join(f"{r:.4f} m/{n}" for r, n in legs))
    speed = replay_speed_factor(rec.bag)
    print(f"corridor run: {rec.goals_reached}/{rec.goals} goals, {rec.sim_s:.0f} s, bag {bag_mb(rec.bag):.1f} MB "
          f"({bag_mb(rec.bag) / (rec.sim_s / 60):.1f} MB/min), record CPU {rec.record_cpu_s / rec.sim_s:.3f} cores, "
          f"counts {counts}; replay RMS {rms_m:.4f} m over {matched} poses; replay x{speed:.1f}")
    assert rec.goals_reached == rec.goals == 7
    assert matched > 1000 and rms_m < 0.01


def _stats(session, keys, service: str) -> dict:  # zenoh.Session, Keys
    for reply in session.get(keys(f"@stats/{service}"), timeout=5.0):
        if reply.ok is not None:
            return json.loads(reply.ok.payload.to_bytes())
    raise AssertionError(f"no stats from {service}")


#: replay rate of the FR079 bag: real time, as the robot's own lidar and odometry would arrive
FR079_RATE = 1.0


def test_fr079_ros1_bag_replayed_into_live_slam(tmp_path: Path, shared_dir: Path,
                                                request: pytest.FixtureRequest) -> None:
    """The real robot's ROS 1 bag played by ``zagv replay`` into localization in mapping mode builds the map live;
    the trajectory it saves with the map (``localization/save_map``) is scored by ``zagv map eval --trajectory``
    exactly like the ``zagv map build`` trajectory of the same log."""
    from services.localization.slam.evaluation import parse_relations, relative_pose_error, scan_poses
    from services.localization.slam.logs import read_log
    from services.localization.slam.mapper import SlamConfig

    bag = shared_dir / "data" / "logs" / "fr079.orig.bag"
    relations_file = shared_dir / "data" / "logs" / "fr079.relations"
    offline_json = tmp_path / "offline.json"
    # the offline figure is computed while the bag plays (the two take a core each instead of one after the other)
    offline_eval = subprocess.Popen([sys.executable, "-m", "services.cli", "map", "eval", str(bag),
                                     str(relations_file), "--json", str(offline_json)], cwd=REPO_ROOT, env=_env())
    request.addfinalizer(lambda: offline_eval.poll() is None and offline_eval.kill())

    maps_dir = tmp_path / "maps"
    config = tmp_path / "mapping.toml"
    # the SLAM settings of `zagv map build`: FR079's odometry is a real robot's (the offline build's odometry prior,
    # not the simulated robot's tight one, and no motion gates), and the synchronous mode, in which every scan of the
    # log reaches the mapper as it does offline, whatever the load on the machine
    slam = SlamConfig()
    config.write_text(f'[clock]\nuse_sim_time = true\n\n[localization]\nmode = "mapping"\nmaps_dir = "{maps_dir}"\n'
                      f"mapping_sync = true\nmapping_min_travel_m = 0.0\nmapping_min_turn_rad = 0.0\n"
                      f"mapping_odom_sigma_xy_m = {slam.odom_prior_sigma_xy_m}\n"
                      f"mapping_odom_sigma_theta_rad = {slam.odom_prior_sigma_theta_rad}\n")
    log = read_log(bag)
    last_scan_s = log.scans[-1].stamp_s
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
        subprocess.run([sys.executable, "-m", "services.cli", "replay", str(bag), "scan", "odom", "--rate",
                        str(FR079_RATE), "--quiet", "--connect", stack.endpoint], cwd=REPO_ROOT, env=_env(),
                       check=True, stdin=subprocess.DEVNULL, timeout=3600)
        replay_s = time.monotonic() - t0
        # the mapper has handled the last scan once its map -> odom (stamped with that scan) is out
        wait_for_sync(lambda: map_odom and map_odom[-1].stamp >= last_scan_s - 1e-6, timeout_s=3600.0)
        all_stats = _stats(session, stack.keys, "localization")
        stats = all_stats["mapping"]
        reply = asyncio.run(query(session, stack.keys, "localization/save_map", m.SaveMapRequest(name="fr079_live"),
                                  timeout_s=60.0))
        assert reply.ok, reply.message
        for s in subs:
            s.undeclare()
    assert offline_eval.wait(timeout=3600) == 0, "zagv map eval (offline) failed"
    offline = json.loads(offline_json.read_text())
    trajectory = maps_dir / "fr079_live.trajectory.txt"
    live_json = tmp_path / "live.json"
    subprocess.run([sys.executable, "-m", "services.cli", "map", "eval", str(bag), str(relations_file),
                    "--trajectory", str(trajectory), "--json", str(live_json)], cwd=REPO_ROOT, env=_env(),
                   check=True, timeout=600)
    live = json.loads(live_json.read_text())
    # for comparison, the estimate the service published at each scan (before later loop closures corrected it)
    tf_stamps = np.array([t.stamp for t in map_odom])
    tf_poses = np.array([[t.x, t.y, t.theta] for t in map_odom])
    scan_stamps = np.array([s.stamp_s for s in log.scans])
    idx = np.clip(np.searchsorted(tf_stamps, scan_stamps + 1e-6) - 1, 0, len(tf_stamps) - 1)
    robot = compose(tf_poses[idx], np.array([s.odom_pose for s in log.scans]))
    with relations_file.open() as f:
        online = relative_pose_error(scan_stamps, scan_poses(robot, log.sensor_pose), parse_relations(f))
    print(f"\nfr079 live SLAM via replay (x{FR079_RATE:g}, {replay_s:.0f} s): map grew to "
          f"{max(maps) if maps else 0} known cells in {len(maps)} maps; saved trajectory RPE "
          f"{live['translation_mean_m']:.4f} m / {live['rotation_mean_rad']:.4f} rad over {live['n_relations']} "
          f"relations vs offline {offline['translation_mean_m']:.4f} m / {offline['rotation_mean_rad']:.4f} rad over "
          f"{offline['n_relations']}; published online estimate {online.translation_mean_m:.4f} m / "
          f"{online.rotation_mean_rad:.4f} rad; mapping stats {stats}; scans in the log {len(log.scans)}, "
          f"received by Zenoh {all_stats['received']}, delivered on the loop {all_stats['delivered']}")
    assert len(maps) >= 3 and maps[-1] > maps[0]  # built live
    assert live["n_relations"] >= 0.95 * offline["n_relations"]  # (nearly) every scan reached the mapper
    assert live["translation_mean_m"] <= 1.10 * offline["translation_mean_m"]
    assert live["rotation_mean_rad"] <= 1.10 * offline["rotation_mean_rad"]
