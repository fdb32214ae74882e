"""Costmap layers: static thresholds, inflation formula and codes, obstacle marking/clearing, rolling window."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.nav.costmap import (
    FREE,
    INSCRIBED,
    LETHAL,
    NO_INFORMATION,
    Costmap2D,
    Footprint,
    GlobalCostmap,
    InflationLayer,
    ObstacleLayer,
    RollingCostmap,
    ScanObservation,
    StaticLayer,
)

RES = 0.05


def global_costmap(occ: np.ndarray, inscribed: float = 0.3, radius: float = 0.6, k: float = 3.0) -> GlobalCostmap:
    cm = GlobalCostmap(Costmap2D.empty(1, 1, RES), StaticLayer(), ObstacleLayer(), InflationLayer(inscribed, radius, k),
                       Footprint(inscribed))
    cm.set_map(occ, RES, 0.0, 0.0)
    return cm


def test_static_layer_codes() -> None:
    occ = np.array([[0, 50, 65, 100, -1]], dtype=np.int8)
    layer = StaticLayer(lethal_threshold=65)
    layer.set_map(occ, RES, 0.0, 0.0)
    assert layer.grid.cost.tolist() == [[FREE, FREE, LETHAL, LETHAL, NO_INFORMATION]]
    untracked = StaticLayer(track_unknown=False)
    untracked.set_map(occ, RES, 0.0, 0.0)
    assert untracked.grid.cost[0, 4] == FREE


def test_inflation_follows_nav2_formula() -> None:
    occ = np.zeros((41, 41), dtype=np.int8)
    occ[20, 20] = 100
    cm = global_costmap(occ, inscribed=0.3, radius=0.6, k=3.0)
    c = cm.master.cost
    assert c[20, 20] == LETHAL
    for cells in range(1, 15):
        d = cells * RES
        got = int(c[20, 20 + cells])
        if d <= 0.3 + 1e-9:
            assert got == INSCRIBED, cells
        elif d <= 0.6 + 1e-9:
            assert got == int(252 * math.exp(-3.0 * (d - 0.3))), cells
        else:
            assert got == FREE, cells
    # diagonal uses the Euclidean distance
    d = math.hypot(8, 8) * RES
    assert int(c[28, 28]) == int(252 * math.exp(-3.0 * (d - 0.3)))


def test_inflation_keeps_unknown_unless_inscribed() -> None:
    occ = np.full((20, 20), -1, dtype=np.int8)
    occ[:, :10] = 0
    occ[10, 5] = 100
    cm = global_costmap(occ, inscribed=0.2, radius=0.5)
    assert cm.master.cost[10, 15] == NO_INFORMATION
    assert cm.master.cost[10, 9] == INSCRIBED
    assert 0 < cm.master.cost[10, 0] < INSCRIBED or cm.master.cost[10, 0] == FREE


def test_inflation_bounds_match_full_update() -> None:
    rng = np.random.default_rng(3)
    occ = (rng.random((80, 90)) > 0.98).astype(np.int8) * 100
    full = global_costmap(occ)
    part = global_costmap(occ)
    part.static.update(part.master)
    before = part.master.cost.copy()
    part.inflation.update(part.master, (20, 30, 50, 60))
    assert np.array_equal(part.master.cost[20:50, 30:60], full.master.cost[20:50, 30:60])
    assert np.array_equal(part.master.cost[:20], before[:20])


def scan_from(x: float, y: float, ranges: list[float], angles: list[float], range_max: float = 20.0
              ) -> ScanObservation:
    return ScanObservation(x, y, np.asarray(angles, float), np.asarray(ranges, np.float32), 0.05, range_max)


def test_obstacle_marks_and_clears_with_inf_and_max_range() -> None:
    occ = np.zeros((100, 100), dtype=np.int8)
    cm = global_costmap(occ)
    # an obstacle 2 m ahead along +x from (1, 2.5)
    cm.add_scan(scan_from(1.0, 2.525, [2.0], [0.0]))
    cm.update()
    i, j = cm.master.world_to_map(3.0, 2.525)
    assert cm.master.cost[i, j] == LETHAL
    # it went away: the beam now has no return (+inf) -> cleared up to raytrace range
    cm.add_scan(scan_from(1.0, 2.525, [math.inf], [0.0]))
    cm.update()
    assert cm.master.cost[i, j] == FREE
    # back, then a SICK-style "no echo" at range_max also clears
    cm.add_scan(scan_from(1.0, 2.525, [2.0], [0.0]))
    cm.add_scan(scan_from(1.0, 2.525, [20.0], [0.0], range_max=20.0))
    cm.update()
    assert cm.master.cost[i, j] == FREE
    # NaN and below range_min are ignored (neither mark nor clear)
    cm.add_scan(scan_from(1.0, 2.525, [2.0], [0.0]))
    cm.add_scan(scan_from(1.0, 2.525, [math.nan, 0.01], [0.0, 0.0]))
    cm.update()
    assert cm.master.cost[i, j] == LETHAL


def test_obstacle_beyond_marking_range_is_not_marked_but_clears() -> None:
    occ = np.zeros((100, 100), dtype=np.int8)
    cm = global_costmap(occ)
    cm.obstacles.obstacle_max_range_m = 2.5
    cm.add_scan(scan_from(0.5, 2.525, [2.8], [0.0]))
    cm.update()
    i, j = cm.master.world_to_map(3.3, 2.525)
    assert cm.obstacles.grid[i, j] == FREE


def test_static_walls_are_not_cleared_by_rays() -> None:
    occ = np.zeros((100, 100), dtype=np.int8)
    occ[50, 60] = 100
    cm = global_costmap(occ)
    cm.add_scan(scan_from(0.5, 2.525, [math.inf], [0.0]))
    cm.update()
    assert cm.master.cost[50, 60] == LETHAL


def test_rolling_window_keeps_obstacles_in_place() -> None:
    static = StaticLayer()
    static.set_map(np.zeros((200, 200), dtype=np.int8), RES, 0.0, 0.0)
    cm = RollingCostmap(3.0, RES, static, ObstacleLayer(), InflationLayer(0.3, 0.5, 3.0), Footprint(0.3))
    cm.recentre(5.0, 5.0)
    cm.add_scan(scan_from(5.0, 5.0, [1.0], [0.0]))
    cm.update()
    assert int(cm.master.cost_at(6.01, 5.01)) == LETHAL
    cm.recentre(5.6, 5.3)
    cm.update()
    assert int(cm.master.cost_at(6.01, 5.01)) == LETHAL
    assert int((cm.master.cost == LETHAL).sum()) == 1
    cm.recentre(9.0, 9.0)  # far away: forgotten
    cm.update()
    assert int((cm.master.cost == LETHAL).sum()) == 0


def test_footprint_clearing_removes_marks_under_the_robot() -> None:
    cm = global_costmap(np.zeros((100, 100), dtype=np.int8))
    cm.add_scan(scan_from(1.0, 2.5, [1.2], [0.0]))
    cm.clear_footprint(2.2, 2.5, 0.0)
    cm.update()
    assert int(cm.master.cost_at(2.2, 2.5)) != LETHAL


def test_polygon_footprint_radii_and_contains() -> None:
    fp = Footprint(polygon=((0.5, 0.3), (-0.5, 0.3), (-0.5, -0.3), (0.5, -0.3)))
    assert fp.inscribed_radius_m == pytest.approx(0.3)
    assert fp.circumscribed_radius_m == pytest.approx(math.hypot(0.5, 0.3))
    assert fp.contains(np.array([[0.4, 0.2], [0.0, 0.35], [-0.49, -0.29]])).tolist() == [True, False, True]
    outline = fp.outline(0.05)
    assert len(outline) >= 64 and fp.contains(outline * 0.99).all()
    with pytest.raises(ValueError):
        Footprint(polygon=((0, 0), (1, 1)))


def test_incremental_global_update_equals_a_full_one() -> None:
    rng = np.random.default_rng(7)
    occ = np.zeros((200, 240), dtype=np.int8)
    occ[(rng.random(occ.shape) > 0.995)] = 100
    occ[:, :3] = -1
    incremental = global_costmap(occ)
    for k in range(12):
        x, y = 1.0 + 0.8 * k, 2.0 + 0.3 * (k % 4)
        angles = np.linspace(-math.pi, math.pi, 90, endpoint=False)
        ranges = rng.uniform(0.3, 4.0, angles.size)
        ranges[rng.random(angles.size) > 0.8] = math.inf
        incremental.add_scan(scan_from(x, y, list(ranges), list(angles)))
        incremental.clear_footprint(x, y, 0.0)
        incremental.update()
        full = global_costmap(occ)
        full.clear_obstacles()  # the next update recomputes every cell
        full.obstacles.grid = incremental.obstacles.grid.copy()
        full.update()
        assert np.array_equal(incremental.master.cost, full.master.cost), f"step {k}"
    incremental.clear_obstacles()
    incremental.update()
    assert np.array_equal(incremental.master.cost, global_costmap(occ).master.cost)


def test_compiled_ray_clearing_and_marking_match_numpy(monkeypatch: pytest.MonkeyPatch) -> None:
    """``_navops.raytrace`` against the NumPy reference on scans whose rays leave the grid, end in no return, or
    end at the sensor: the obstacle grids are identical after every scan."""
    from services.nav import costmap as costmap_module

    if costmap_module._navops is None:
        pytest.skip("the _navops C extension was not built (no C compiler at install)")
    rng = np.random.default_rng(9)
    master = Costmap2D.empty(90, 70, RES, origin_x=-0.3, origin_y=0.2)
    compiled, plain = ObstacleLayer(), ObstacleLayer()
    for k in range(15):
        x, y = rng.uniform(-0.5, 4.8), rng.uniform(0.0, 3.8)
        angles = np.linspace(-math.pi, math.pi, 181, endpoint=False) + rng.uniform(-0.01, 0.01)
        ranges = rng.uniform(0.0, 5.0, angles.size)
        ranges[rng.random(angles.size) > 0.85] = math.inf
        ranges[rng.random(angles.size) > 0.95] = 20.0
        obs = scan_from(x, y, list(ranges), list(angles), range_max=20.0)
        compiled.add_scan(master, obs)
        with monkeypatch.context() as m:
            m.setattr(costmap_module, "_navops", None)
            plain.add_scan(master, obs)
        assert compiled.grid is not None and plain.grid is not None
        assert np.array_equal(compiled.grid, plain.grid), f"scan {k}"
        assert compiled.marked_cells == plain.marked_cells
    assert compiled.marked_cells > 0 and (compiled.grid == FREE).any()
