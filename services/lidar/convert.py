"""``LMDscandata`` -> ``LaserScan`` in REP-103 (counter-clockwise positive, 0 rad straight ahead).

The LMS1xx measures its own angles counter-clockwise (seen from above, scanner upright) with 90 deg straight
ahead, from -45 deg to +225 deg, so ``angle_rep103 = angle_sick - 90 deg`` (-135 deg .. +135 deg); beam ``i`` is at
``start + i * step``. Distances are ``value * scale + offset`` in mm. As ROS drivers report them, a zero reading
(no echo) and a reading beyond ``range_max`` become +inf; a non-zero reading below ``range_min`` becomes -inf
("too close", REP-117). Consumers keep only finite ranges.
"""

from __future__ import annotations

import math

import numpy as np

from proto.messages import LaserScan, Pose2D
from services.lidar.cola import ColaError
from services.lidar.telegrams import ScanData

SICK_FORWARD_DEG = 90.0


def to_laserscan(
    scan: ScanData,
    *,
    stamp: float,
    range_min_m: float,
    range_max_m: float,
    mount: Pose2D,
    intensities: bool,
    frame: str = "laser",
) -> LaserScan:
    """Build the LaserScan of ``scan`` (needs a DIST1 channel; RSSI1 becomes ``intensities`` when asked)."""
    dist = scan.channel("DIST1")
    if dist is None:
        raise ColaError("LMDscandata has no DIST1 channel (check LMDscandatacfg output channel)")
    if dist.step_raw == 0 and dist.values.size > 1:
        raise ColaError("LMDscandata DIST1 angular step is 0")
    if scan.scan_frequency_raw == 0:
        raise ColaError("LMDscandata scan frequency is 0")
    mm = dist.values * dist.scale + dist.offset
    with np.errstate(over="ignore"):  # an absurd scale factor overflows float32 to inf: "no return"
        ranges = (mm * 1e-3).astype(np.float32)
    ranges[(dist.values == 0) | (ranges > range_max_m)] = np.inf
    ranges[ranges < range_min_m] = -np.inf
    step_rad = math.radians(dist.step_raw / 1e4)
    angle_min = math.radians(dist.start_angle_raw / 1e4 - SICK_FORWARD_DEG)
    scan_time = 100.0 / scan.scan_frequency_raw
    rssi = b""
    if intensities:
        ch = scan.channel("RSSI1")
        if ch is not None and ch.values.size == dist.values.size:
            with np.errstate(over="ignore"):
                rssi = ch.scaled.astype(np.float32).tobytes()
    return LaserScan(
        stamp=stamp,
        frame=frame,
        angle_min=angle_min,
        angle_max=angle_min + step_rad * max(dist.values.size - 1, 0),
        angle_increment=step_rad,
        time_increment=(dist.step_raw / 1e4) / 360.0 * scan_time,
        scan_time=scan_time,
        range_min=range_min_m,
        range_max=range_max_m,
        ranges=ranges.tobytes(),
        intensities=rssi,
        mount=mount,
        scan_counter=scan.scan_counter,
    )
