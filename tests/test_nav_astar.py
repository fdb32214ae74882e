"""A*: optimal against a reference Dijkstra, clear failure reasons, escape from the inscribed zone, smoothing."""

from __future__ import annotations

import heapq
import math

import numpy as np
import pytest

from services.nav.astar import AStarPlanner, cells_to_path, line_cells, planning_cost, smooth_cells
from services.nav.costmap import INSCRIBED, LETHAL, NO_INFORMATION, Costmap2D


def reference_dijkstra(cost: np.ndarray, start: tuple[int, int], goal: tuple[int, int], weight: float) -> float:
    """Plain Dijkstra over the same cost model: step * (1 + weight * c / 252), cells >= 253 impassable."""
    h, w = cost.shape
    dist = {start: 0.0}
    heap = [(0.0, start)]
    while heap:
        d, (i, j) = heapq.heappop(heap)
        if (i, j) == goal:
            return d
        if d > dist.get((i, j), math.inf):
            continue
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                if di == dj == 0:
                    continue
                ni, nj = i + di, j + dj
                if not (0 <= ni < h and 0 <= nj < w) or cost[ni, nj] >= INSCRIBED:
                    continue
                nd = d + math.hypot(di, dj) * (1 + weight * min(int(cost[ni, nj]), 252) / 252)
                if nd < dist.get((ni, nj), math.inf):
                    dist[(ni, nj)] = nd
                    heapq.heappush(heap, (nd, (ni, nj)))
    return math.inf


def path_cost(cost: np.ndarray, cells: np.ndarray, weight: float) -> float:
    steps = np.diff(cells, axis=0)
    assert np.abs(steps).max() <= 1, "8-connected steps only"
    lengths = np.hypot(steps[:, 0], steps[:, 1])
    c = np.minimum(cost[cells[1:, 0], cells[1:, 1]], 252) / 252
    return float(np.sum(lengths * (1 + weight * c)))


@pytest.mark.parametrize("seed", range(8))
def test_optimal_on_random_grids(seed: int) -> None:
    rng = np.random.default_rng(seed)
    cost = rng.integers(0, 200, (30, 40)).astype(np.uint8)
    cost[rng.random((30, 40)) < 0.25] = LETHAL
    cost[0, 0] = cost[29, 39] = 0
    planner = AStarPlanner(cost_weight=3.0)
    res = planner.plan(cost, (0, 0), (29, 39))
    ref = reference_dijkstra(cost, (0, 0), (29, 39), 3.0)
    if math.isinf(ref):
        assert not res.ok and "no path" in res.error
        return
    assert res.ok, res.error
    assert res.cost == pytest.approx(ref, rel=1e-6)
    assert path_cost(cost, res.cells, 3.0) == pytest.approx(ref, rel=1e-6)
    assert (cost[res.cells[:, 0], res.cells[:, 1]] < INSCRIBED).all()
    # equal inputs, equal paths
    assert np.array_equal(planner.plan(cost, (0, 0), (29, 39)).cells, res.cells)


def test_cost_aware_detour() -> None:
    cost = np.zeros((20, 20), dtype=np.uint8)
    cost[:8, 10] = 250  # expensive band, passable; going round it costs less than crossing at weight 10
    cheap = AStarPlanner(cost_weight=0.0).plan(cost, (5, 2), (5, 17))
    aware = AStarPlanner(cost_weight=10.0).plan(cost, (5, 2), (5, 17))
    assert (cost[cheap.cells[:, 0], cheap.cells[:, 1]] == 250).any()
    assert not (cost[aware.cells[:, 0], aware.cells[:, 1]] == 250).any()


def test_failure_reasons() -> None:
    cost = np.zeros((10, 10), dtype=np.uint8)
    cost[:, 5] = LETHAL
    p = AStarPlanner()
    assert "no path" in p.plan(cost, (0, 0), (9, 9)).error
    assert "outside" in p.plan(cost, (0, 0), (10, 3)).error
    assert "outside" in p.plan(cost, (-1, 0), (1, 3)).error
    assert "goal is inside an obstacle" in p.plan(cost, (0, 0), (3, 5)).error
    assert "start is inside an obstacle" in p.plan(cost, (3, 5), (0, 0)).error
    cost[2, 2] = INSCRIBED
    assert "too close" in p.plan(cost, (0, 0), (2, 2)).error
    cost[4, 1] = NO_INFORMATION
    assert "unknown" in p.plan(cost, (0, 0), (4, 1)).error
    assert AStarPlanner(allow_unknown=True).plan(cost, (0, 0), (4, 1)).ok


def test_start_in_inscribed_zone_can_leave_but_not_enter_other_inscribed_cells() -> None:
    cost = np.zeros((20, 20), dtype=np.uint8)
    cost[8:12, 0:6] = INSCRIBED  # the robot stands here (pushed against something)
    cost[0:20, 10] = INSCRIBED  # a separate inscribed wall that must not be crossed
    cost[5, 10] = 0
    res = AStarPlanner().plan(cost, (10, 2), (10, 8))
    assert res.ok, res.error
    res2 = AStarPlanner().plan(cost, (10, 2), (10, 15))
    assert res2.ok
    crossed = res2.cells[res2.cells[:, 1] == 10]
    assert (crossed[:, 0] == 5).all()


def test_smoothing_keeps_clearance_and_endpoints() -> None:
    rng = np.random.default_rng(5)
    cost = np.zeros((60, 60), dtype=np.uint8)
    for _ in range(25):
        i, j = rng.integers(5, 55, 2)
        cost[max(i - 3, 0):i + 3, max(j - 3, 0):j + 3] = LETHAL
    cost[:3, :3] = 0
    cost[-3:, -3:] = 0
    from scipy import ndimage

    d = ndimage.distance_transform_edt(cost != LETHAL)
    graded = np.where(cost == LETHAL, LETHAL, np.clip(250 - 40 * d, 0, 252)).astype(np.uint8)
    res = AStarPlanner().plan(graded, (1, 1), (58, 58))
    assert res.ok
    smooth = smooth_cells(graded, res.cells)
    assert len(smooth) < len(res.cells)
    assert (smooth[0] == res.cells[0]).all() and (smooth[-1] == res.cells[-1]).all()
    worst_before = int(graded[res.cells[:, 0], res.cells[:, 1]].max())
    for a, b in zip(smooth[:-1], smooth[1:]):
        ii, jj = line_cells(*a, *b)
        assert int(graded[ii, jj].max()) <= worst_before


def test_path_poses_and_planning_cost() -> None:
    cm = Costmap2D.empty(20, 20, 0.05)
    cells = np.array([[1, 1], [1, 2], [2, 3], [3, 4]])
    path = cells_to_path(cm, cells, (0.07, 0.07), (0.22, 0.17, 1.0), spacing_m=0.02)
    assert path[0, :2] == pytest.approx([0.07, 0.07])
    assert path[-1] == pytest.approx([0.22, 0.17, 1.0])
    assert np.hypot(*np.diff(path[:, :2], axis=0).T).max() <= 0.02 + 1e-9
    dist = np.full((20, 20), 1.0, dtype=np.float32)
    dist[5, 5] = 0.35
    out = planning_cost(cm, dist, 0.3, 0.2)
    assert out[5, 5] > 0 and out[0, 0] == 0
