"""The front end keeps a corridor's length: with exact odometry and a ray-cast world of known scale, the mapped
distance along the corridor world's main corridor (x = 4 to 15 m) matches the true one.

A scan matcher that shortened or stretched every keyframe edge by a fraction of a percent would bend nothing
locally but open metres of gap along a long corridor before a loop could close it (0.3 % is 0.3 m per 100 m).

Known defect, hence the strict xfail: today the mapped corridor is 0.68-0.79 % too long (11.075-11.087 m of 11.000;
0.27-0.31 % with ``match_visibility_margin_m = 0.3``), with the odometry exact, so the bias is the matcher's. On
the corrected CARMEN logs, given their reference poses as odometry, the sequential edges come out 0.06-0.51 %
shorter than the reference, summing to 9.6 m over the infinite corridor's 1920 m. When the matcher is fixed this
test passes and the strict marker makes it fail until the marker is removed.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.common.world import World
from services.localization.slam.logs import LaserLog, LaserScanRecord
from services.localization.slam.offline import run_slam
from services.localization.synthetic import Laser, route

#: lobby, then east along the main corridor to x = 15 m (no revisit: no loop closure can correct the length)
OUT_LEG = [(0.0, 0.0, 0.0), (4.0, 0.1, 0.0), (4.0, 0.1, math.pi / 2), (4.0, 3.2, math.pi / 2), (4.0, 3.2, 0.0),
           (15.0, 3.2, 0.0)]


@pytest.mark.xfail(strict=True, reason="the scan matcher stretches a corridor by 0.7-0.8 % with exact odometry")
@pytest.mark.parametrize("step_m", [0.25, 1.0])
def test_the_mapped_corridor_has_its_true_length(step_m: float) -> None:
    world = World.load_builtin("corridor")
    laser = Laser(world, beams=361, fov_rad=math.pi, range_max=20.0, rng=np.random.default_rng(3))
    truth = np.array(list(route(OUT_LEG, step_m=step_m, step_rad=0.1)))
    scans = [LaserScanRecord(0.1 * k, np.asarray(laser.scan(tuple(p), (0.0, 0.0, 0.0)), float), laser.angles, p,
                             laser.range_min, laser.range_max)
             for k, p in enumerate(truth)]
    _, poses = run_slam(LaserLog(scans, np.zeros(3))).slam.trajectory()
    corridor = np.flatnonzero((np.abs(truth[:, 1] - 3.2) < 1e-6) & (np.abs(truth[:, 2]) < 1e-6))
    a, b = corridor[0], corridor[-1]
    true_m = math.hypot(*(truth[b, :2] - truth[a, :2]))
    mapped_m = math.hypot(*(poses[b, :2] - poses[a, :2]))
    assert true_m > 10.0
    assert abs(mapped_m / true_m - 1.0) < 0.003, f"mapped {mapped_m:.3f} m of a {true_m:.3f} m corridor"
