"""Accuracy of the offline SLAM on the Kümmerle et al. 2009 benchmark logs (relative-pose error of the estimated
trajectory against the published ground-truth relations): clean odometry must meet the acceptance figures (better
than gmapping's published ones), and degraded odometry (``OdometryNoise.degraded``: wheel scale ±5 %, heading drift
2°/m, jumps), also with rotation errors on top (``OdometryNoise.turning``), must stay within 1.5x of them with no
accepted loop closure that contradicts the clean result."""

from __future__ import annotations

import pytest

from services.localization.slam.map_bench import bench_log

#: (log, acceptance bound of the mean translational error in m with clean odometry; gmapping's published figure)
LOGS = [
    ("mit-csail.clf", 0.035),  # gmapping 0.049
    ("fr079.orig.bag", 0.050),  # gmapping 0.061
    ("aces.orig.bag", 0.040),  # gmapping 0.060
]
IDS = ["mit-csail", "fr079", "aces"]


def _log(shared_dir, name):
    path = shared_dir / "data" / "logs" / name
    if not path.is_file():
        pytest.skip(f"{name} not found in {path.parent}")
    return path


@pytest.mark.slow
@pytest.mark.timeout(1800)  # ~1 min per log on an idle 2-core machine; far longer under load
@pytest.mark.parametrize(("log_name", "bound_m"), LOGS, ids=IDS)
def test_translational_error_with_clean_odometry(shared_dir, log_name, bound_m):
    row, _ = bench_log(_log(shared_dir, log_name), "clean")
    assert row.closures_accepted > 0
    assert row.translation_error_m <= bound_m, row
    assert row.rotation_error_rad < 0.02, row


@pytest.mark.long
@pytest.mark.timeout(3600)
@pytest.mark.parametrize(("log_name", "bound_m"), LOGS, ids=IDS)
def test_degraded_odometry_within_one_and_a_half_times_and_no_false_closure(shared_dir, log_name, bound_m):
    path = _log(shared_dir, log_name)
    clean, clean_laser = bench_log(path, "clean")
    assert clean.translation_error_m <= bound_m, clean
    # degraded, and degraded with rotation errors too (turning on the spot costs heading: OdometryNoise.turning)
    for setting in ("degraded", "turning"):
        degraded, _ = bench_log(path, setting, seed=1, reference=clean_laser)
        assert degraded.translation_error_m <= 1.5 * clean.translation_error_m, (clean, degraded)
        assert degraded.closures_false == 0, degraded
