"""Where a reference trajectory disagrees with its own scans: the poses it cannot judge a loop closure by.

A corrected log's poses are themselves a SLAM result. At a few poses they are visibly off: the scan, placed at its
reference pose, does not line up with the scans before and after it placed at theirs, and lines up well a few
degrees or centimetres away. A loop closure that ends at such a pose disagrees with the reference because the
reference is wrong there, so ``zagv map bench`` counts it apart (``unjudged``) instead of as a false closure.

The test for scan i: the scans i-n..i+n except i, placed in scan i's frame by the reference
(``between(reference[i], reference[m])``), make a likelihood field; scan i is matched into it by a correlative
search around the identity (± ``window_xy_m``, ± ``window_theta_rad``) and Gauss-Newton refinement. The reference
pose is suspect when that best fit lies more than ``max_xy_m`` or ``max_theta_rad`` from the identity and scores at
least ``min_gain`` higher than the identity does.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

import numpy as np

from services.common.se2 import between, transform_points, wrap_angle

from .likelihood import MultiResolutionGrid
from .matcher import refine, score, search_and_refine


def suspect_reference_poses(points_of: Callable[[int], np.ndarray], reference: np.ndarray, scans: Iterable[int], *,
                            neighbours: int = 5, resolution_m: float = 0.05, levels: int = 3,
                            window_xy_m: float = 0.3, window_theta_rad: float = 0.3,
                            theta_step_rad: float = 0.01, max_xy_m: float = 0.1, max_theta_rad: float = 0.03,
                            min_gain: float = 0.02) -> set[int]:
    """The scans among ``scans`` whose pose in ``reference`` (N, 3), robot frame, disagrees with the scans around
    them; ``points_of(i)`` gives scan i's hit points (M, 2) in the robot frame."""
    reference = np.asarray(reference, float)
    suspect: set[int] = set()
    for i in sorted(set(int(s) for s in scans)):
        around = [m for m in range(max(0, i - neighbours), min(len(reference), i + neighbours + 1)) if m != i]
        clouds = [transform_points(between(reference[i], reference[m]), points_of(m)) for m in around]
        clouds = [c for c in clouds if len(c)]
        points = points_of(i)
        if not clouds or len(points) == 0:
            continue
        grid = MultiResolutionGrid.from_points(np.concatenate(clouds), resolution_m, levels)
        identity = np.zeros(3)
        best = search_and_refine(grid, points, identity, window_xy_m=window_xy_m, window_theta_rad=window_theta_rad,
                                 theta_step_rad=theta_step_rad, n_best=4, incumbent=refine(grid, points, identity))
        assert best is not None  # the incumbent at worst
        moved = (float(np.hypot(best.pose[0], best.pose[1])) > max_xy_m
                 or abs(float(wrap_angle(best.pose[2]))) > max_theta_rad)
        if moved and best.score >= score(grid.levels[0], points, identity) + min_gain:
            suspect.add(i)
    return suspect
