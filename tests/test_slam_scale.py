"""The front end keeps a corridor's length: with exact odometry and a ray-cast world of known scale, the mapped
distance along the corridor world's main corridor (x = 4 to 15 m) matches the true one.

A scan matcher that shortened or stretched every keyframe edge by a fraction of a percent would bend nothing
locally but open metres of gap along a long corridor before a loop could close it (0.3 % is 0.3 m per 100 m).

Walking out along a corridor, the scan sees surfaces the submap's keyframes never did: a door recess's back wall
coming out of its jamb's shadow, the wall behind a pillar. The likelihood field pulls such points back onto the part
the submap holds, against the direction of travel, and each match comes out long. With those points left out of
weakly constrained matches (``SlamConfig.match_visibility_margin_m``) the corridor maps +0.18 / +0.25 % long (0.25 /
1 m steps); without, +0.79 / +0.68 %, which the second test keeps in view so that the first can fail.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.common.world import World
from services.localization.slam.logs import LaserLog, LaserScanRecord
from services.localization.slam.mapper import SlamConfig
from services.localization.slam.offline import run_slam
from services.localization.synthetic import Laser, route

#: lobby, then east along the main corridor to x = 15 m (no revisit: no loop closure can correct the length)
OUT_LEG = [(0.0, 0.0, 0.0), (4.0, 0.1, 0.0), (4.0, 0.1, math.pi / 2), (4.0, 3.2, math.pi / 2), (4.0, 3.2, 0.0),
           (15.0, 3.2, 0.0)]


def _mapped_over_true(step_m: float, config: SlamConfig) -> float:
    """Mapped / true length of the main corridor stretch driven at ``step_m`` per scan with exact odometry."""
    world = World.load_builtin("corridor")
    laser = Laser(world, beams=361, fov_rad=math.pi, range_max=20.0, rng=np.random.default_rng(3))
    truth = np.array(list(route(OUT_LEG, step_m=step_m, step_rad=0.1)))
    scans = [LaserScanRecord(0.1 * k, np.asarray(laser.scan(tuple(p), (0.0, 0.0, 0.0)), float), laser.angles, p,
                             laser.range_min, laser.range_max)
             for k, p in enumerate(truth)]
    _, poses = run_slam(LaserLog(scans, np.zeros(3)), config).slam.trajectory()
    corridor = np.flatnonzero((np.abs(truth[:, 1] - 3.2) < 1e-6) & (np.abs(truth[:, 2]) < 1e-6))
    a, b = corridor[0], corridor[-1]
    true_m = math.hypot(*(truth[b, :2] - truth[a, :2]))
    assert true_m > 10.0
    return math.hypot(*(poses[b, :2] - poses[a, :2])) / true_m


POLISH = {"off": SlamConfig(), "corridor axis": SlamConfig(polish_nearest_hit=True),
          "full": SlamConfig(polish_nearest_hit=True, polish_axis_only=False)}


@pytest.mark.parametrize("polish", list(POLISH))
@pytest.mark.parametrize("step_m", [0.25, 1.0])
def test_the_mapped_corridor_has_its_true_length(step_m: float, polish: str) -> None:
    """Without the polish on the nearest-hit field (the default), with it along corridors
    (``SlamConfig.polish_nearest_hit``) and with it on every match in full (``polish_axis_only`` False): its
    shortest-ray visibility test keeps the recesses' hidden backs out of it (by the longest ray the full polish
    mapped +0.96 / +0.67 %). Off +0.18 / +0.25 %, corridor axis -0.13 / -0.06 %, full +0.14 / -0.00 %."""
    ratio = _mapped_over_true(step_m, POLISH[polish])
    assert abs(ratio - 1.0) < 0.003, f"the corridor maps {100 * (ratio - 1):+.2f} % long"


def test_without_the_visibility_refinement_the_corridor_maps_long() -> None:
    ratio = _mapped_over_true(0.25, SlamConfig(match_visibility_margin_m=0.0, polish_nearest_hit=False))
    assert ratio - 1.0 > 0.005, f"the corridor maps {100 * (ratio - 1):+.2f} % long without it"
