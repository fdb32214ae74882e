"""Accuracy of the offline SLAM on the Kümmerle et al. 2009 benchmark logs (relative-pose error of the estimated
trajectory against the published ground-truth relations), which must beat gmapping's published figures."""

from __future__ import annotations

import pytest

from services.localization.slam.evaluation import parse_relations, relative_pose_error, scan_poses
from services.localization.slam.logs import read_log
from services.localization.slam.offline import run_slam

#: (log, relations, gmapping's mean translational error in m)
LOGS = [
    ("mit-csail.clf", "mit-csail.relations", 0.049),
    ("fr079.orig.bag", "fr079.relations", 0.061),
]


@pytest.mark.slow
@pytest.mark.timeout(900)  # ~1 min per log on an idle 2-core machine; far longer under load
@pytest.mark.parametrize(("log_name", "relations_name", "gmapping_error_m"), LOGS, ids=["mit-csail", "fr079"])
def test_translational_error_beats_gmapping(shared_dir, log_name, relations_name, gmapping_error_m):
    logs = shared_dir / "data" / "logs"
    if not (logs / log_name).is_file():
        pytest.skip(f"{log_name} not found in {logs}")
    log = read_log(logs / log_name)
    run = run_slam(log)
    stamps, poses = run.slam.trajectory()
    with (logs / relations_name).open() as f:
        error = relative_pose_error(stamps, scan_poses(poses, log.sensor_pose), parse_relations(f))
    assert error.n_missing == 0
    assert len(run.slam.loop_closures) > 0
    assert error.translation_mean_m < gmapping_error_m, error
    assert error.rotation_mean_rad < 0.02, error
