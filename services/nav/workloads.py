"""Deterministic A* workloads for ``zagv bench --only astar`` (docs/performance.md), reproducible anywhere.

``warehouse_costmap()``: a 1000 x 1000 inflated costmap at 0.05 m (50 m x 50 m), row 0 at y = 0, cell (row r,
col c) centred at ((c + 0.5) res, (r + 0.5) res):

1. obstacles: a 2-cell outer wall; 60 rectangles drawn from ``numpy.random.default_rng(seed)``, each
   ``w, h = rng.uniform(0.5, 4.0, 2)`` then ``cx, cy = rng.uniform(0, 50, 2)`` (m), filling rows
   ``round(y0 / res):round(y1 / res)`` and columns ``round(x0 / res):round(x1 / res)`` clipped to the map; three
   0.2 m walls across the whole height at x = 12.4, 24.9 and 37.4 m with 3 m doors at y = 42-45, 5-8 and 42-45 m,
   so the path snakes through all three;
2. inflation (Nav2's form): ``d`` = Euclidean distance between cell centres to the nearest obstacle (m);
   254 on an obstacle, 253 where ``d <= 0.63``, ``floor(252 exp(-3 (d - 0.63)))`` where ``d <= 1.5``, else 0;
3. start and goal: the cost-0 cells whose centres are nearest (0.5, 0.5) m and (49.5, 49.5) m (first in row-major
   order on a tie); seeds from 42 upwards until the two are 8-connected through cells of cost < 253 (43 is the
   first). A third of the map is >= 253; the optimal path costs 3429.774242 cell units (x 0.05 for m) over 2913
   cells, about 489,000 expansions.

This is the workload of the published C -O2 / pure-Python A* reference measurements, so its figures compare.

``real_map_workload(yaml)``: a ROS map (map_server YAML) inflated with the robot's radii as nav does, start and goal
the free cells nearest the map's lower-left and upper-right corners within the largest free 8-connected region.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage

from services.nav.costmap import (
    INSCRIBED,
    LETHAL,
    Costmap2D,
    Footprint,
    GlobalCostmap,
    InflationLayer,
    ObstacleLayer,
    StaticLayer,
)

WAREHOUSE_CELLS, WAREHOUSE_RES_M = 1000, 0.05
WAREHOUSE_FIRST_SEED = 42
WAREHOUSE_RECTS, RECT_MIN_M, RECT_MAX_M = 60, 0.5, 4.0
WAREHOUSE_BORDER_CELLS = 2
#: (x_min, y_min, x_max, y_max) in m; the gaps between the pieces of each wall are its door
WAREHOUSE_WALLS_M = ((12.4, 0.0, 12.6, 42.0), (12.4, 45.0, 12.6, 50.0),
                     (24.9, 0.0, 25.1, 5.0), (24.9, 8.0, 25.1, 50.0),
                     (37.4, 0.0, 37.6, 42.0), (37.4, 45.0, 37.6, 50.0))
WAREHOUSE_INSCRIBED_M, WAREHOUSE_INFLATION_M, WAREHOUSE_COST_SCALING = 0.63, 1.5, 3.0


@dataclass(frozen=True)
class Workload:
    """A costmap (uint8, row 0 at the origin), start and goal cells (row, col), resolution (m) and a name."""

    name: str
    cost: np.ndarray
    start: tuple[int, int]
    goal: tuple[int, int]
    resolution: float
    seed: int = 0


def _fill_rect_m(grid: np.ndarray, res: float, x0: float, y0: float, x1: float, y1: float) -> None:
    h, w = grid.shape
    grid[max(0, round(y0 / res)):min(h, round(y1 / res)), max(0, round(x0 / res)):min(w, round(x1 / res))] = True


def _inflate_nav2(obstacle: np.ndarray, res: float) -> np.ndarray:
    d = ndimage.distance_transform_edt(~obstacle) * res
    cost = np.where(d <= WAREHOUSE_INFLATION_M,
                    np.floor(252.0 * np.exp(-WAREHOUSE_COST_SCALING * (d - WAREHOUSE_INSCRIBED_M))), 0.0)
    cost[d <= WAREHOUSE_INSCRIBED_M] = INSCRIBED
    cost[obstacle] = LETHAL
    return cost.astype(np.uint8)


def _nearest_cell(mask: np.ndarray, res: float, x_m: float, y_m: float) -> tuple[int, int]:
    """(row, col) of the ``mask`` cell whose centre is nearest (x_m, y_m); the first in row-major order on a tie."""
    rows, cols = np.nonzero(mask)
    d2 = ((cols + 0.5) * res - x_m) ** 2 + ((rows + 0.5) * res - y_m) ** 2
    k = int(np.argmin(d2))
    return int(rows[k]), int(cols[k])


def _connected(cost: np.ndarray, a: tuple[int, int], b: tuple[int, int]) -> bool:
    labels, _ = ndimage.label(cost < INSCRIBED, structure=np.ones((3, 3), dtype=int))
    return bool(labels[a] == labels[b] != 0)


def warehouse_costmap(first_seed: int = WAREHOUSE_FIRST_SEED) -> Workload:
    """The documented 1000 x 1000 workload (module docstring)."""
    n, res = WAREHOUSE_CELLS, WAREHOUSE_RES_M
    seed = first_seed
    while True:
        obstacle = np.zeros((n, n), dtype=bool)
        b = WAREHOUSE_BORDER_CELLS
        obstacle[:b, :] = obstacle[-b:, :] = obstacle[:, :b] = obstacle[:, -b:] = True
        rng = np.random.default_rng(seed)
        for _ in range(WAREHOUSE_RECTS):
            w_m, h_m = rng.uniform(RECT_MIN_M, RECT_MAX_M, 2)
            cx, cy = rng.uniform(0.0, n * res, 2)
            _fill_rect_m(obstacle, res, cx - w_m / 2, cy - h_m / 2, cx + w_m / 2, cy + h_m / 2)
        for wall in WAREHOUSE_WALLS_M:
            _fill_rect_m(obstacle, res, *wall)
        cost = _inflate_nav2(obstacle, res)
        free = cost == 0
        start = _nearest_cell(free, res, 0.5, 0.5)
        goal = _nearest_cell(free, res, n * res - 0.5, n * res - 0.5)
        if _connected(cost, start, goal):
            return Workload("warehouse_1000", cost, start, goal, res, seed)
        seed += 1


def real_map_workload(yaml_path: str | Path, inscribed_radius_m: float = 0.63, inflation_radius_m: float = 0.645,
                      cost_scaling_factor: float = 10.0) -> Workload:
    """A ROS map inflated like nav's global costmap, corner to corner (module docstring)."""
    from services.common.map_io import load_map  # only the bench reads map files

    occ = load_map(yaml_path)
    cm = GlobalCostmap(Costmap2D.empty(1, 1, occ.resolution), StaticLayer(), ObstacleLayer(),
                       InflationLayer(inscribed_radius_m, inflation_radius_m, cost_scaling_factor),
                       Footprint(inscribed_radius_m))
    cm.set_map(occ.data, occ.resolution, occ.origin[0], occ.origin[1])
    cost = cm.master.cost
    labels, n_labels = ndimage.label(cost == 0, structure=np.ones((3, 3), dtype=int))
    if n_labels == 0:
        raise ValueError(f"{yaml_path}: no free cell after inflation")
    largest = np.argmax(np.bincount(labels.ravel())[1:]) + 1
    region = labels == largest
    h, w = cost.shape
    start = _nearest_cell(region, 1.0, 0.0, 0.0)
    goal = _nearest_cell(region, 1.0, float(w), float(h))
    return Workload(Path(yaml_path).parent.name or Path(yaml_path).stem, cost.copy(), start, goal, occ.resolution)
