"""Run ``GraphSlam`` over a whole ``LaserLog`` (in memory; reading and writing files is the caller's job)."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from .logs import LaserLog
from .mapper import GraphSlam, SlamConfig, scan_to_points


def scan_points(log: LaserLog, index: int, *, max_range_m: float = math.inf) -> np.ndarray:
    """Scan ``index`` of ``log`` as robot-frame hit points, as the mapper gets it: readings within 5 cm (or the
    scan's own minimum) and beyond the scan's maximum range (or ``max_range_m``) dropped."""
    scan = log.scans[index]
    return scan_to_points(scan.ranges_m, scan.angles_rad, log.sensor_pose, min_range_m=max(scan.min_range_m, 0.05),
                          max_range_m=min(scan.max_range_m, max_range_m))


@dataclass
class OfflineRun:
    slam: GraphSlam
    processing_s: float
    processing_cpu_s: float
    log_duration_s: float
    n_scans: int

    @property
    def realtime_factor(self) -> float:
        """Log duration ÷ processing time."""
        return self.log_duration_s / max(self.processing_s, 1e-9)

    @property
    def realtime_factor_cpu(self) -> float:
        """Log duration ÷ CPU time of this process (less sensitive to other load on the machine)."""
        return self.log_duration_s / max(self.processing_cpu_s, 1e-9)


def run_slam(log: LaserLog, config: SlamConfig | None = None, *, max_scans: int | None = None) -> OfflineRun:
    """Process the first ``max_scans`` scans (all by default) and optimise; wall time is measured around it."""
    slam = GraphSlam(config)
    scans = log.scans if max_scans is None else log.scans[:max_scans]
    origin = log.sensor_pose[:2]
    start = time.perf_counter()
    start_cpu = time.process_time()
    for index, scan in enumerate(scans):
        slam.add_scan(scan.stamp_s, scan.odom_pose, scan_points(log, index), origin)
    slam.finish()
    elapsed = time.perf_counter() - start
    elapsed_cpu = time.process_time() - start_cpu
    duration = scans[-1].stamp_s - scans[0].stamp_s if scans else 0.0
    return OfflineRun(slam, elapsed, elapsed_cpu, duration, len(scans))
