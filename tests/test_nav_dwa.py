"""Holonomic DWA: dynamic window, exact rollout, critics."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.common.robot import TwistLimits
from services.nav.costmap import LETHAL, Costmap2D, Footprint, InflationLayer
from services.nav.dwa import DwaConfig, DwaPlanner


def planner(**cfg) -> DwaPlanner:
    return DwaPlanner(DwaConfig(**cfg), TwistLimits(), Footprint(0.3))


def free_map(n: int = 100) -> Costmap2D:
    return Costmap2D.empty(n, n, 0.05)


def straight_path(y: float = 2.5, x0: float = 1.0, x1: float = 4.5) -> np.ndarray:
    n = int((x1 - x0) / 0.05) + 1
    return np.column_stack([np.linspace(x0, x1, n), np.full(n, y), np.zeros(n)])


def test_window_respects_acceleration_and_velocity_limits() -> None:
    p = planner(window_dt_s=0.1)
    s = p.samples((0.15, 0.0, 0.45))
    lim = p.limits
    assert s[:, 0].min() >= 0.15 - lim.ax_max_mps2 * 0.1 - 1e-12 and s[:, 0].max() <= lim.vx_max_mps + 1e-12
    assert s[:, 2].max() <= lim.wz_max_radps + 1e-12 and s[:, 2].min() >= 0.45 - lim.alpha_max_radps2 * 0.1 - 1e-12
    assert (s[:, 1] == 0.0).any()  # stopping sideways is always a candidate
    assert len(s) >= 20 * 5 * 10
    # a current velocity beyond the box is brought back inside
    s2 = p.samples((0.5, 0.0, 0.0))
    assert s2[:, 0].max() <= lim.vx_max_mps + 1e-12


def test_rollout_is_exact_on_se2() -> None:
    p = planner(sim_time_s=2.0, sim_steps=20)
    twists = np.array([[0.2, -0.1, 0.4], [0.1, 0.2, 0.0]])
    traj = p.rollout((1.0, 2.0, 0.7), twists)
    for k, (vx, vy, wz) in enumerate(twists):
        x, y, th = 1.0, 2.0, 0.7
        dt = 1e-4
        for _ in range(int(round(2.0 / dt))):
            x += dt * (vx * math.cos(th) - vy * math.sin(th))
            y += dt * (vx * math.sin(th) + vy * math.cos(th))
            th += dt * wz
        assert traj[k, -1] == pytest.approx([x, y, th], abs=1e-4)


def test_follows_a_straight_path_forward() -> None:
    p = planner()
    res = p.plan(free_map(), (1.0, 2.5, 0.0), (0.1, 0.0, 0.0), straight_path(), (4.5, 2.5, 0.0))
    assert res.ok
    vx, vy, wz = res.twist
    assert vx > 0.1 and abs(vy) < 0.05 and abs(wz) < 0.1
    assert set(res.scores) == {"obstacle", "path_distance", "path_alignment", "goal_distance", "goal_heading",
                               "oscillation"}


def test_sidesteps_to_a_path_beside_the_robot() -> None:
    p = planner()
    res = p.plan(free_map(), (1.0, 2.3, 0.0), (0.0, 0.0, 0.0), straight_path(2.5), (4.5, 2.5, 0.0))
    assert res.twist[1] > 0.0


def test_obstacle_critic_rejects_collisions_and_reports_none_valid() -> None:
    cm = free_map()
    cm.cost[:, 32:40] = LETHAL  # wall from x = 1.6 m
    InflationLayer(0.3, 0.5, 3.0).update(cm)
    p = planner()
    res = p.plan(cm, (1.0, 2.5, 0.0), (0.2, 0.0, 0.0), straight_path(), (4.5, 2.5, 0.0))
    end = res.trajectory[-1]
    assert end[0] < 1.6 - 0.3
    # boxed in: every sample collides
    cm2 = Costmap2D.empty(100, 100, 0.05, value=LETHAL)
    res2 = p.plan(cm2, (1.0, 2.5, 0.0), (0.0, 0.0, 0.0), straight_path(), (4.5, 2.5, 0.0))
    assert not res2.ok and "no valid trajectory" in res2.error and res2.twist == (0.0, 0.0, 0.0)


def test_goal_heading_critic_turns_towards_the_goal_heading_near_the_goal() -> None:
    p = planner()
    path = straight_path(2.5, 1.0, 1.2)
    res = p.plan(free_map(), (1.15, 2.5, 0.0), (0.0, 0.0, 0.0), path, (1.2, 2.5, 1.5))
    assert res.twist[2] > 0.0


def test_oscillation_critic_penalises_sign_flips() -> None:
    base = dict(weight_path_distance=0.0, weight_path_alignment=0.0, weight_goal_distance=0.0,
                weight_goal_heading=0.0, weight_obstacle=0.0)
    p = planner(weight_oscillation=1.0, **base)
    res = p.plan(free_map(), (2.5, 2.5, 0.0), (0.0, 0.0, 0.0), straight_path(), (4.5, 2.5, 0.0),
                 previous=(0.1, -0.1, 0.2))
    assert res.twist[0] >= 0 and res.twist[1] <= 0 and res.twist[2] >= 0
    assert res.scores["oscillation"] == 0.0


def test_escapes_from_the_inscribed_zone() -> None:
    cm = free_map()
    cm.cost[:, :22] = LETHAL  # wall up to x = 1.1 m
    InflationLayer(0.3, 0.5, 3.0).update(cm)
    p = planner()
    pose = (1.35, 2.5, 0.0)  # 0.25 m from the wall: inside the inscribed radius 0.3 m
    res = p.plan(cm, pose, (0.0, 0.0, 0.0), straight_path(2.5, 1.35, 4.0), (4.0, 2.5, 0.0))
    assert res.ok and res.twist[0] > 0.0


def test_the_compiled_rollout_and_path_search_match_numpy(monkeypatch: pytest.MonkeyPatch) -> None:
    """``_navops.c`` against the NumPy reference, bit for bit: rollouts that leave a cluttered grid (cells off the map
    are NO_INFORMATION), nearest path points, and the twist a whole plan picks, with and without the extension."""
    from services.nav import dwa as dwa_module

    if dwa_module._navops is None:
        pytest.skip("the _navops C extension was not built (no C compiler at install)")
    rng = np.random.default_rng(4)
    cm = Costmap2D(0.05, -0.4, 0.3, rng.integers(0, 255, (60, 80)).astype(np.uint8))
    p = planner()
    seen = []
    for pose, current in [((1.0, 1.2, 0.3), (0.1, 0.0, 0.0)), ((3.5, 3.2, -2.0), (0.3, -0.1, 0.5)),
                          ((0.0, 0.0, math.pi), (0.0, 0.0, 0.0))]:
        twists = p.samples(current)
        traj, cost = p.rollout_costs(cm, pose, twists)
        reference = p.rollout(pose, twists)
        assert np.array_equal(traj, reference)
        assert np.array_equal(cost, cm.cost_at(reference[..., 0], reference[..., 1]))
        seen.append(cost)
        path = straight_path(y=pose[1])[:25]
        idx, d2 = dwa_module.nearest_points(traj[:, -1, :], path)
        ref_idx, ref_d2 = dwa_module.nearest_points_numpy(traj[:, -1, :], path)
        assert np.array_equal(idx, ref_idx) and np.array_equal(d2, ref_d2)
    all_costs = np.concatenate([c.ravel() for c in seen])
    assert (all_costs == 255).any() and (all_costs < 255).any()  # some poses leave the grid, some do not
    free = free_map()
    path = straight_path()
    compiled = p.plan(free, (1.0, 2.4, 0.1), (0.1, 0.0, 0.0), path, (4.5, 2.5, 0.0), previous=(0.1, 0.0, 0.0))
    monkeypatch.setattr(dwa_module, "_navops", None)
    plain = p.plan(free, (1.0, 2.4, 0.1), (0.1, 0.0, 0.0), path, (4.5, 2.5, 0.0), previous=(0.1, 0.0, 0.0))
    assert compiled.twist == plain.twist and compiled.scores == plain.scores
    assert np.array_equal(compiled.trajectory, plain.trajectory)
