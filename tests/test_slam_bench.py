"""``zagv map bench`` / ``map localize`` on the small corrected logs (the CI slice), and live mapping on one of them.

A corrected log's poses are a reference trajectory; SLAM gets them corrupted as odometry (``OdometryNoise``), and
the result must stay within 0.10 m RMS of the reference; accepted loop closures that contradict it are counted.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from services.cli.main import main
from services.localization.slam.evaluation import aligned_trajectory_error
from services.localization.slam.live import LiveMapper
from services.localization.slam.logs import read_log
from services.localization.slam.map_bench import bench_log
from services.localization.slam.mapper import SlamConfig, scan_to_points
from services.localization.slam.odometry_noise import OdometryNoise, corrupt_odometry

#: a small corrected log (292 scans, 360 beams); orebro (237 scans) is not yet within 0.10 m (see the bench)
SMALL_LOGS = ["freiburg-101"]


@pytest.fixture
def corrected_dir(shared_dir):
    path = shared_dir / "data" / "logs" / "carmen_corrected"
    if not (path / "orebro-corrected.log.gz").is_file():
        pytest.skip(f"corrected CARMEN logs not found in {path}")
    return path


@pytest.mark.timeout(900)  # ~15 s of CPU; far longer on a loaded machine
def test_map_bench_slice_on_small_corrected_logs(corrected_dir, tmp_path, capsys):
    out = tmp_path / "bench.json"
    assert main(["map", "bench", str(corrected_dir), "--only", *SMALL_LOGS, "--json", str(out)]) == 0
    rows = json.loads(out.read_text())
    assert sorted(r["log"].split("-corrected")[0] for r in rows) == sorted(SMALL_LOGS)
    for row in rows:
        assert row["ate_rms_m"] < 0.10, row
        assert row["closures_false"] is not None  # counted against the reference (1 on freiburg-101 today)
        assert 0 <= row["closures_unjudged"] <= row["closures_false"], row  # 0 of 1 on freiburg-101 today
        assert "wheel scale ±3 %" in row["odometry_noise"]
        assert 0.99 < row["reference_scale"] < 1.01 and row["ate_scaled_rms_m"] <= row["ate_rms_m"] + 1e-9
        # the front end's own bias on the keyframe edges: a fraction of a percent (+0.06 % today), not zero
        assert 0.0 < abs(row["edge_along_pct"]) < 1.0 and abs(row["edge_heading_deg_per_100m"]) < 10.0, row
        assert abs(row["edge_turn_pct"]) < 1.0, row
    table = capsys.readouterr().out
    assert "ate_m" in table and "ref_scale" in table and "edge_%" in table and "unjdg" in table
    assert "freiburg-101-corrected.log.gz" in table


@pytest.mark.slow
@pytest.mark.timeout(900)  # ~25 s of CPU
def test_the_polish_takes_most_of_the_short_bias_out_of_corridor_edges(corrected_dir):
    """The density field shortens every match along a corridor (``likelihood.py``); with the reference as odometry
    and no odometry calibration to learn the bias back, the first 300 keyframe edges of infinite-corridor come out
    0.63 % short of the reference without the polish (``SlamConfig.polish_nearest_hit``), 0.41 % with the polish
    along corridors (``polish_axis_only``) and 0.32 % with the full polish of every match."""
    path = corrected_dir / "infinite-corridor-corrected.log.gz"
    configs = {"off": SlamConfig(calibrate_odometry=False),
               "axis": SlamConfig(polish_nearest_hit=True, calibrate_odometry=False),
               "full": SlamConfig(polish_nearest_hit=True, polish_axis_only=False, calibrate_odometry=False)}
    rows = {name: bench_log(path, "exact", max_scans=300, config=config)[0] for name, config in configs.items()}
    off, axis, full = rows["off"], rows["axis"], rows["full"]
    assert off.edge_along_pct < -0.5, off
    assert axis.edge_along_pct > off.edge_along_pct + 0.15 and axis.ate_rms_m < off.ate_rms_m + 0.02, (axis, off)
    assert abs(full.edge_along_pct) < 0.4 and full.edge_along_pct > off.edge_along_pct + 0.2, (full, off)
    assert full.ate_rms_m < off.ate_rms_m + 0.02, (full, off)


@pytest.mark.timeout(900)
def test_map_bench_exact_odometry_gives_slam_the_reference_unchanged(corrected_dir, tmp_path):
    out = tmp_path / "bench.json"
    assert main(["map", "bench", str(corrected_dir), "--only", "freiburg-101", "--odometry", "exact",
                 "--max-scans", "120", "--json", str(out)]) == 0
    (row,) = json.loads(out.read_text())
    assert row["odometry"] == "exact" and row["odometry_noise"] == "as logged"
    assert row["ate_rms_m"] < 0.10, row


@pytest.mark.long
@pytest.mark.timeout(900)
def test_live_mapper_on_a_corrected_log_with_noisy_odometry(corrected_dir):
    """The live mapping mode runs the same front and back end: same accuracy bar as the offline bench."""
    log = read_log(corrected_dir / "freiburg-101-corrected.log.gz")
    reference = np.array([s.odom_pose for s in log.scans])
    noisy, _ = corrupt_odometry(log, OdometryNoise.for_reference(seed=2))
    mapper = LiveMapper(start_pose=tuple(reference[0]), min_travel_m=0.0, min_turn_rad=0.0)
    for scan in noisy.scans:
        points = scan_to_points(scan.ranges_m, scan.angles_rad, noisy.sensor_pose,
                                min_range_m=0.05, max_range_m=scan.max_range_m)
        assert mapper.add_scan(scan.stamp_s, scan.odom_pose, points, noisy.sensor_pose[:2])
    mapper.slam.finish()
    _, poses = mapper.slam.trajectory()
    assert aligned_trajectory_error(poses, reference).rms_m < 0.10
    assert mapper.render() is not None


@pytest.mark.long
@pytest.mark.timeout(900)
def test_amcl_on_real_scans_against_the_reference_map(corrected_dir, capsys):
    assert main(["map", "localize", str(corrected_dir), "--only", "freiburg-101"]) == 0
    table = capsys.readouterr().out
    row = next(line for line in table.splitlines() if line.startswith("freiburg-101"))
    rms_m, lost = float(row.split()[4]), row.split()[-1]
    assert rms_m < 0.2 and lost == "0%", row


def test_map_bench_set_overrides_slam_config_fields():
    from services.localization.slam.map_bench import parse_overrides

    assert parse_overrides(None) is None
    config = parse_overrides(["submap_keyframes=30", "resolution_m=0.025", "calibrate_odometry=false"])
    assert config is not None
    assert (config.submap_keyframes, config.resolution_m, config.calibrate_odometry) == (30, 0.025, False)
    assert config.levels == 3  # untouched fields keep their defaults
    for bad in (["submap_keyframes"], ["no_such_field=1"], ["submap_keyframes=\"many\""]):
        with pytest.raises(ValueError):
            parse_overrides(bad)


def test_map_bench_finds_ros2_bag_folders_and_their_relations(tmp_path):
    """A ROS 2 bag is a folder (``metadata.yaml`` and its storage files): the bench lists the folder once, never the
    ``.mcap``/``.db3`` inside, and reads its relations from ``NAME.relations`` beside it."""
    from services.localization.slam.map_bench import find_logs, relations_for

    (tmp_path / "intel.clf").write_text("")
    (tmp_path / "intel.relations").write_text("")
    hospital = tmp_path / "sub" / "hospital"
    hospital.mkdir(parents=True)
    (hospital / "metadata.yaml").write_text("")
    (hospital / "hospital_0.mcap").write_text("")
    (hospital / "hospital_0.db3").write_text("")
    (tmp_path / "sub" / "hospital.relations").write_text("")
    (tmp_path / "notes.txt").write_text("")
    assert find_logs(tmp_path) == [tmp_path / "intel.clf", hospital]
    assert relations_for(hospital) == tmp_path / "sub" / "hospital.relations"
    assert relations_for(tmp_path / "intel.clf") == tmp_path / "intel.relations"
    (tmp_path / "sub" / "hospital.relations").unlink()
    assert relations_for(hospital) is None
