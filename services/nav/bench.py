"""Nav benchmarks: inflation of a 1000x1000 costmap, A* corner to corner on it, one DWA cycle (20x5x20 samples)."""

from __future__ import annotations

import numpy as np

from services.common.bench import BenchRow, time_calls
from services.nav.astar import AStarPlanner
from services.nav.costmap import Costmap2D, Footprint, GlobalCostmap, InflationLayer, ObstacleLayer, StaticLayer
from services.nav.dwa import DwaConfig, DwaPlanner, Limits

RESOLUTION = 0.05


def obstacle_map(n: int = 1000, seed: int = 7) -> np.ndarray:
    """An n x n occupancy grid (int8) with ~80 random rectangular obstacles and free corners."""
    rng = np.random.default_rng(seed)
    occ = np.zeros((n, n), dtype=np.int8)
    for _ in range(80):
        i, j = rng.integers(0, n, 2)
        occ[i:i + rng.integers(5, 60), j:j + rng.integers(5, 60)] = 100
    occ[:40, :40] = 0
    occ[-40:, -40:] = 0
    return occ


def inflated_costmap(n: int = 1000) -> GlobalCostmap:
    cm = GlobalCostmap(Costmap2D.empty(1, 1, RESOLUTION), StaticLayer(), ObstacleLayer(),
                       InflationLayer(0.63, 0.645, 10.0), Footprint(0.63))
    cm.set_map(obstacle_map(n), RESOLUTION, 0.0, 0.0)
    return cm


def bench_costmap() -> list[BenchRow]:
    cm = inflated_costmap()
    t = time_calls(lambda: cm.inflation.update(cm.master), repeat=10, warmup=1)
    return [BenchRow("costmap.inflate_ms", float(np.median(t) * 1e3), "ms", "1000x1000 cells, r = 0.645 m")]


def bench_astar() -> list[BenchRow]:
    cm = inflated_costmap()
    planner = AStarPlanner()
    n = cm.master.width
    result = planner.plan(cm.master.cost, (20, 20), (n - 21, n - 21), RESOLUTION)
    if not result.ok:
        raise RuntimeError(f"bench map has no corner-to-corner path: {result.error}")
    t = time_calls(lambda: planner.plan(cm.master.cost, (20, 20), (n - 21, n - 21), RESOLUTION), repeat=3,
                   warmup=0, max_s=30.0)
    return [BenchRow("astar.plan_ms", float(np.median(t) * 1e3), "ms",
                     f"1000x1000, corner to corner, {result.expanded} expansions (C reference 55 ms)")]


def bench_dwa() -> list[BenchRow]:
    cm = inflated_costmap(100)
    cfg = DwaConfig(vx_samples=20, vy_samples=5, wz_samples=20, sim_time_s=1.7)
    dwa = DwaPlanner(cfg, Limits(), Footprint(0.63))
    path = np.column_stack([np.linspace(1.0, 4.0, 61), np.full(61, 1.0), np.zeros(61)])
    pose = (1.0, 1.0, 0.0)
    res = dwa.plan(cm.master, pose, (0.1, 0.0, 0.0), path, (4.0, 1.0, 0.0), previous=(0.1, 0.0, 0.0))
    n = len(dwa.samples((0.1, 0.0, 0.0)))
    t = time_calls(lambda: dwa.plan(cm.master, pose, (0.1, 0.0, 0.0), path, (4.0, 1.0, 0.0),
                                    previous=(0.1, 0.0, 0.0)), repeat=50, warmup=3)
    return [BenchRow("dwa.cycle_ms", float(np.median(t) * 1e3), "ms",
                     f"<= 10 ms; {n} samples x {cfg.sim_steps} steps, {res.valid_samples} valid")]


BENCHES = [("costmap", bench_costmap), ("dwa", bench_dwa), ("astar", bench_astar)]
