"""Whether an order node can be reached on the map: free space wide enough for the chassis and connected to the robot.

A cell is traversable when it is known free (0 <= occupancy < ``occupied_threshold``) and its Euclidean distance to
the nearest non-free cell exceeds ``clearance_m`` (the chassis radius less one cell, so that the grid's
quantisation never closes a passage that nav's planner can use). Traversable cells form 8-connected regions
(``scipy.ndimage.label``); a node is reachable when its cell lies in the robot's region. This is the check made
before an order is accepted, so an unreachable node is refused before the robot moves.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage


class Reachability:
    """Connected traversable regions of one occupancy grid (row 0 at ``origin``, +x along a row)."""

    def __init__(self, cells: np.ndarray, resolution_m: float, origin_x_m: float, origin_y_m: float,
                 clearance_m: float, occupied_threshold: int = 65) -> None:
        grid = np.asarray(cells, dtype=np.int16)
        if grid.ndim != 2 or not resolution_m > 0:
            raise ValueError(f"need a 2-D grid and a positive resolution, got shape {grid.shape}, {resolution_m}")
        self.resolution_m = float(resolution_m)
        self.origin = (float(origin_x_m), float(origin_y_m))
        free = (grid >= 0) & (grid < occupied_threshold)
        self.distance_m = ndimage.distance_transform_edt(free) * self.resolution_m
        self.clearance_m = max(0.0, clearance_m - self.resolution_m)
        traversable = self.distance_m > self.clearance_m
        self.labels, self.regions = ndimage.label(traversable, structure=np.ones((3, 3), dtype=bool))

    def cell(self, x_m: float, y_m: float) -> tuple[int, int] | None:
        """(row, column) of a point, or None outside the grid."""
        if not (math.isfinite(x_m) and math.isfinite(y_m)):
            return None
        col = math.floor((x_m - self.origin[0]) / self.resolution_m)
        row = math.floor((y_m - self.origin[1]) / self.resolution_m)
        if 0 <= row < self.labels.shape[0] and 0 <= col < self.labels.shape[1]:
            return row, col
        return None

    def region_near(self, x_m: float, y_m: float, search_m: float = 0.5) -> int:
        """The region of the point, else of the nearest traversable cell within ``search_m`` (0: none)."""
        c = self.cell(x_m, y_m)
        if c is None:
            return 0
        if self.labels[c]:
            return int(self.labels[c])
        r = max(1, math.ceil(search_m / self.resolution_m))
        r0, r1 = max(0, c[0] - r), min(self.labels.shape[0], c[0] + r + 1)
        c0, c1 = max(0, c[1] - r), min(self.labels.shape[1], c[1] + r + 1)
        window = self.labels[r0:r1, c0:c1]
        rows, cols = np.nonzero(window)
        if rows.size == 0:
            return 0
        k = int(np.argmin((rows + r0 - c[0]) ** 2 + (cols + c0 - c[1]) ** 2))
        return int(window[rows[k], cols[k]])

    def why_unreachable(self, start: tuple[float, float], goal: tuple[float, float]) -> str:
        """Empty when ``goal`` is reachable from ``start`` (x, y in m), else the reason."""
        c = self.cell(*goal)
        if c is None:
            return f"({goal[0]:.2f}, {goal[1]:.2f}) is outside the map"
        if not self.labels[c]:
            return (f"({goal[0]:.2f}, {goal[1]:.2f}) is {self.distance_m[c]:.2f} m from an obstacle or unknown space, "
                    f"the chassis needs {self.clearance_m + self.resolution_m:.2f} m")
        here = self.region_near(*start)
        if here == 0:
            return f"the robot at ({start[0]:.2f}, {start[1]:.2f}) is not in free space on the map"
        if int(self.labels[c]) != here:
            return f"({goal[0]:.2f}, {goal[1]:.2f}) is in free space that no path connects to the robot"
        return ""
