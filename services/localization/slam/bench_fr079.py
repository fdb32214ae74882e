"""Bench rows of the SLAM core on the FR079 log of the Kümmerle et al. 2009 benchmark.

``slam.realtime_factor`` = log duration ÷ wall time of SLAM over the whole log (matching, loop closure and
optimisation; reading the bag and rendering the grid excluded), plus the relative-pose errors of the result.
The data folder is ``$ZAGV_SHARED/data/logs`` (default: ``shared`` next to the repository); without it the
group returns no rows and says so.
"""

from __future__ import annotations

import sys
from pathlib import Path

from services.common.bench import BenchRow
from services.common.devdata import shared_dir


def _logs_dir() -> Path:
    return shared_dir() / "data" / "logs"


def bench_slam() -> list[BenchRow]:
    from services.localization.slam.evaluation import parse_relations, relative_pose_error, scan_poses
    from services.localization.slam.logs import read_log
    from services.localization.slam.offline import run_slam

    logs = _logs_dir()
    bag, relations_file = logs / "fr079.orig.bag", logs / "fr079.relations"
    if not bag.is_file():
        print(f"bench slam: {bag} not found (set ZAGV_SHARED); no rows", file=sys.stderr)
        return []
    log = read_log(bag)
    run = run_slam(log)
    stamps, poses = run.slam.trajectory()
    with relations_file.open() as f:
        error = relative_pose_error(stamps, scan_poses(poses, log.sensor_pose), parse_relations(f))
    return [
        BenchRow("slam.realtime_factor", run.realtime_factor, "x", ">= 10 (fr079)"),
        BenchRow("slam.realtime_factor_cpu", run.realtime_factor_cpu, "x", "log duration / CPU time"),
        BenchRow("slam.scan_ms", 1e3 * run.processing_s / run.n_scans, "ms", "per scan, fr079"),
        BenchRow("slam.fr079_translation_error_m", error.translation_mean_m, "m", "< 0.061 (gmapping), 0.056 graph"),
        BenchRow("slam.fr079_rotation_error_rad", error.rotation_mean_rad, "rad", "Kümmerle 2009 metric"),
        BenchRow("slam.fr079_closures_accepted", len(run.slam.loop_closures), "", "loop closures in the graph"),
        BenchRow("slam.fr079_closures_rejected", len(run.slam.rejected_closures), "",
                 "inconsistent or contradicting the graph"),
    ]


BENCHES = [("slam", bench_slam)]
