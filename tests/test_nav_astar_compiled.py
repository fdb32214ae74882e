"""The compiled A* search loop against the pure-Python reference loop: same cells, same cost, same expansions."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from services.nav.astar import AStarPlanner
from services.nav.costmap import INSCRIBED, LETHAL, NO_INFORMATION
from services.nav.workloads import warehouse_costmap


def assert_same(cost: np.ndarray, start: tuple[int, int], goal: tuple[int, int], **kw: object) -> None:
    compiled = AStarPlanner(**kw).plan(cost, start, goal, 0.05)
    python = AStarPlanner(compiled=False, **kw).plan(cost, start, goal, 0.05)
    assert compiled.error == python.error
    assert compiled.expanded == python.expanded
    assert compiled.cost == python.cost
    np.testing.assert_array_equal(compiled.cells, python.cells)


def test_the_compiled_loop_is_built() -> None:
    assert AStarPlanner().uses_compiled, "services/nav/_astar.c was not built: run `make install` (needs gcc)"
    assert not AStarPlanner(compiled=False).uses_compiled


@pytest.mark.parametrize("seed", range(12))
def test_same_path_as_the_reference_loop_on_random_grids(seed: int) -> None:
    rng = np.random.default_rng(100 + seed)
    h, w = rng.integers(5, 80, 2)
    cost = rng.choice(np.array([0, 0, 0, 0, 30, 120, 252, INSCRIBED, LETHAL, NO_INFORMATION], dtype=np.uint8),
                      (h, w))
    start = (int(rng.integers(h)), int(rng.integers(w)))
    goal = (int(rng.integers(h)), int(rng.integers(w)))
    cost[goal] = rng.choice([0, 100])
    cost[start] = rng.choice([0, 50, INSCRIBED])  # an inscribed start exercises the escape
    weight = float(rng.choice([0.0, 3.0, 7.3]))
    for allow_unknown in (False, True):
        assert_same(cost, start, goal, cost_weight=weight, allow_unknown=allow_unknown)


def test_same_path_on_uniform_cost_ties_and_strided_input() -> None:
    cost = np.zeros((60, 90), dtype=np.uint8)  # many equal-f paths: the tie-break decides
    assert_same(cost, (0, 0), (59, 89))
    assert_same(cost, (30, 5), (30, 80))
    big = np.zeros((120, 180), dtype=np.uint8)
    big[::2, ::2][10:50, 40] = LETHAL
    assert_same(big[::2, ::2], (0, 0), (59, 89))  # a non-contiguous view


def test_unreachable_goal_reports_the_search() -> None:
    cost = np.zeros((20, 20), dtype=np.uint8)
    cost[:, 10] = LETHAL
    res = AStarPlanner().plan(cost, (5, 2), (5, 17))
    assert not res.ok and "not reachable" in res.error and res.expanded == 200
    assert_same(cost, (5, 2), (5, 17))


def test_concurrent_plans_from_threads() -> None:
    wl = warehouse_costmap()
    small = np.zeros((50, 50), dtype=np.uint8)
    expected = AStarPlanner(compiled=False).plan(small, (0, 0), (49, 49))
    results = []

    def plan_small() -> None:
        for _ in range(20):
            results.append(AStarPlanner().plan(small, (0, 0), (49, 49)))

    worker = threading.Thread(target=plan_small)
    worker.start()
    big = AStarPlanner().plan(wl.cost, wl.start, wl.goal)
    worker.join()
    assert big.ok and abs(big.cost - 3429.774242) < 1e-6
    assert len(results) == 20
    for r in results:
        np.testing.assert_array_equal(r.cells, expected.cells)


def test_warehouse_workload_matches_the_reference_loop_and_the_published_cost() -> None:
    wl = warehouse_costmap()
    assert wl.seed == 43 and wl.start == (32, 32) and wl.goal == (967, 967)
    assert wl.cost.shape == (1000, 1000) and 0.33 < float(np.mean(wl.cost >= INSCRIBED)) < 0.34
    compiled = AStarPlanner().plan(wl.cost, wl.start, wl.goal, 1.0)
    python = AStarPlanner(compiled=False).plan(wl.cost, wl.start, wl.goal, 1.0)
    assert abs(compiled.cost - 3429.774242) < 1e-6  # the C reference's optimal cost on this workload
    assert len(compiled.cells) == 2913
    assert compiled.expanded == python.expanded and compiled.cost == python.cost
    np.testing.assert_array_equal(compiled.cells, python.cells)


@pytest.mark.parametrize("weight", [-0.5, float("nan"), float("inf")])
def test_a_cost_weight_that_would_shorten_steps_is_refused(weight: float) -> None:
    with pytest.raises(ValueError, match="cost_weight must be a finite number >= 0"):
        AStarPlanner(cost_weight=weight)
    import services.nav._astar as compiled_loop  # the extension checks on its own: its heap needs keys >= 0

    with pytest.raises(ValueError, match="cost_weight must be a finite number >= 0"):
        compiled_loop.plan(np.zeros((4, 4), dtype=np.uint8), 4, 4, (0, 0), (3, 3), weight, False, None)
