"""``zagv scenario``: the scenario file format, the Table 3 summary and the plots (no stack needed)."""

from __future__ import annotations

import math
from pathlib import Path

import msgspec
import numpy as np
import pytest

from proto import messages as m
from services.common.map_io import OccupancyMap
from services.common.robot import RobotSpec
from services.scenario.client import Leg
from services.scenario.mapping import (
    arrived,
    costmap_follows,
    jog_command,
    route_clearance_problems,
    route_length_m,
)
from services.scenario.model import Goal, ScenarioError, load_scenario
from services.scenario.report import draw_plots, format_table, summarize

REPO = Path(__file__).resolve().parents[1]


def write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "s.toml"
    p.write_text(text)
    return p


def test_corridor_table3_scenario_is_the_papers_experiment() -> None:
    sc = load_scenario(REPO / "scenarios" / "corridor_table3.toml")
    assert sc.world == "corridor" and sc.map_yaml is None
    assert sc.start == (0.0, 0.0, 0.0) and sc.repeats == 10
    assert [g.pose for g in sc.goals] == [(3.0, 0.1, 1.57), (3.0, 3.5, 0.0), (13.6, 3.2, -1.0), (24.4, 3.5, 1.57),
                                          (26.8, 6.6, 1.0), (23.1, 13.4, -1.57), (0.0, 3.2, 2.0)]
    (box,) = sc.dynamic_obstacles
    assert box.rect == (9.0, 1.6, 10.0, 3.0) and box.appear_after_s == 5.0
    # the leg it appears in runs west through the straight corridor past x = 9..10
    a, b = sc.goals[box.during_goal - 2].pose, sc.goals[box.during_goal - 1].pose
    assert min(a[0], b[0]) < 9.0 and max(a[0], b[0]) > 10.0


def test_map_scenarios_resolve_relative_to_the_file(tmp_path: Path) -> None:
    (tmp_path / "maps").mkdir()
    (tmp_path / "maps" / "x.yaml").write_text("image: x.pgm\n")
    sc = load_scenario(write(tmp_path, 'map = "maps/x.yaml"\n[[goals]]\npose = [1, 2, 3]\n'))
    assert sc.map_yaml == str((tmp_path / "maps" / "x.yaml").resolve())
    assert sc.goals == [Goal("1", (1.0, 2.0, 3.0))] and sc.repeats == 1 and sc.speed == 1.0


@pytest.mark.parametrize(("text", "needle"), [
    ('world = "corridor"\n', "no [[goals]]"),
    ('[[goals]]\npose = [1, 2, 3]\n', "exactly one of"),
    ('world = "corridor"\nmap = "x.yaml"\n[[goals]]\npose = [1, 2, 3]\n', "exactly one of"),
    ('world = "corridor"\n[[goals]]\npose = [1, 2]\n', "goals[1].pose"),
    ('world = "corridor"\nstrat = [0, 0, 0]\n[[goals]]\npose = [1, 2, 3]\n', "unknown key(s) strat"),
    ('world = "corridor"\n[[goals]]\npose = [1, 2, 3]\n[[dynamic_obstacles]]\nrect = [1, 1, 0, 2]\n', "rect"),
    ('world = "corridor"\n[[goals]]\npose = [1, 2, 3]\n[[dynamic_obstacles]]\nrect = [0, 0, 1, 1]\nduring_goal = 2\n',
     "during_goal 2"),
    ('map = "missing.yaml"\n[[goals]]\npose = [1, 2, 3]\n', "not found"),
    ('world = "corridor"\nrepeats = 0\n[[goals]]\npose = [1, 2, 3]\n', "repeats"),
    ('world = \n', "TOML syntax"),
    ('world = "corridor"\n[mapping]\nroute = [[1, 0, 0]]\nsave = "x"\n[[goals]]\npose = [1, 2, 3]\n',
     "mapping: unknown key(s) save"),
    ('world = "corridor"\n[mapping]\nroute = []\n[[goals]]\npose = [1, 2, 3]\n', "mapping.route must be"),
    ('world = "corridor"\n[mapping]\nroute = [[1, 0, 0], [2, 0]]\n[[goals]]\npose = [1, 2, 3]\n',
     "mapping.route[2]"),
    ('world = "corridor"\n[mapping]\nroute = [[1, 0, 0]]\nsave_as = "../x"\n[[goals]]\npose = [1, 2, 3]\n',
     "mapping.save_as"),
    ('world = "corridor"\n[mapping]\nroute = [[1, 0, 0]]\njog_speed_mps = 0.5\n[[goals]]\npose = [1, 2, 3]\n',
     "mapping.jog_speed_mps"),
    ('world = "corridor"\n[mapping]\nroute = [[1, 0, 0]]\njog_speed_mps = 0\n[[goals]]\npose = [1, 2, 3]\n',
     "mapping.jog_speed_mps"),
    ('world = "corridor"\nmapping = [1]\n[[goals]]\npose = [1, 2, 3]\n', "mapping must be a table"),
])
def test_bad_scenarios_name_the_problem(tmp_path: Path, text: str, needle: str) -> None:
    with pytest.raises(ScenarioError) as err:
        load_scenario(write(tmp_path, text))
    assert needle in str(err.value)


def test_built_map_scenario_maps_the_corridor_then_runs_table3() -> None:
    sc = load_scenario(REPO / "scenarios" / "corridor_table3_built_map.toml")
    table3 = load_scenario(REPO / "scenarios" / "corridor_table3.toml")
    assert sc.world == "corridor" and sc.start == (0.0, 0.0, 0.0) and sc.repeats == 1 and not sc.dynamic_obstacles
    assert [g.pose for g in sc.goals] == [g.pose for g in table3.goals]
    assert sc.mapping is not None and sc.mapping.save_as == "corridor_built" and sc.mapping.jog_speed_mps == 0.2
    route = sc.mapping.route
    assert max(w[0] for w in route) >= 25.0  # the whole main corridor
    assert math.hypot(route[-1][0] - 23.1, route[-1][1] - 13.4) < 0.5  # up the north corridor to goal 6


def test_mapping_defaults_name_the_map_after_the_scenario(tmp_path: Path) -> None:
    p = tmp_path / "my run.toml"
    p.write_text('world = "corridor"\n[mapping]\nroute = [[1, 0, 0]]\n[[goals]]\npose = [1, 2, 3]\n')
    sc = load_scenario(p)
    assert sc.name == "my run" and sc.mapping is not None
    assert sc.mapping.save_as == "my_run_built" and sc.mapping.route == [(1.0, 0.0, 0.0)]
    assert sc.mapping.jog_speed_mps == RobotSpec().vx_max_mps
    assert load_scenario(write(tmp_path, 'world = "corridor"\n[[goals]]\npose = [1, 2, 3]\n')).mapping is None


def test_jog_command_drives_straight_at_the_speed_within_the_limits() -> None:
    spec = RobotSpec()
    # target 2 m ahead and 2 m to the left of a robot facing north: world (2, 2) -> body (2, -2)
    vx, vy, wz = jog_command((0.0, 0.0, math.pi / 2), (2.0, 2.0, math.pi / 2), spec, 0.2)
    assert math.hypot(vx, vy) == pytest.approx(0.2) and vx == pytest.approx(-vy) and vx > 0 and wz == 0.0
    # backwards the Table 2 box allows only 0.1 m/s: the direction is kept, the speed scaled down
    vx, vy, _ = jog_command((0.0, 0.0, 0.0), (-3.0, 1.0, 0.0), spec, 0.2)
    assert vx == pytest.approx(spec.vx_min_mps) and vy == pytest.approx(-vx / 3)
    # near the waypoint the speed is the distance per second; the turn is clamped to wz_max
    vx, vy, wz = jog_command((0.0, 0.0, 0.0), (0.05, 0.0, 3.0), spec, 0.2)
    assert (vx, vy) == pytest.approx((0.05, 0.0)) and wz == spec.wz_max_radps
    assert jog_command((1.0, 1.0, 0.3), (1.0, 1.0, 0.3), spec, 0.2) == (0.0, 0.0, 0.0)
    assert arrived((0.0, 0.0, 0.0), (0.05, 0.05, 0.05)) and not arrived((0.0, 0.0, 0.0), (0.0, 0.0, 0.2))


def test_route_clearance_names_the_leg_that_touches_a_wall() -> None:
    solid = np.ones((60, 100), bool)  # 5 x 3 m at 0.05 m, free inside a 0.5 m border
    solid[10:50, 10:90] = False
    start = (1.5, 1.5, 0.0)
    assert route_clearance_problems(start, [(3.5, 1.5, 0.0)], solid, 0.05, (0.0, 0.0), 0.63) == []
    problems = route_clearance_problems(start, [(3.5, 1.5, 0.0), (3.5, 2.3, 0.0), (6.0, 2.3, 0.0)], solid, 0.05,
                                        (0.0, 0.0), 0.63)
    assert len(problems) == 2 and problems[0].startswith("leg 2") and "from a wall" in problems[0]
    assert problems[1].startswith("leg 3") and "outside the map" in problems[1]
    assert route_length_m(start, [(3.5, 1.5, 0.0), (3.5, 2.3, 0.0)]) == pytest.approx(2.8)


def test_costmap_follows_a_map_when_its_geometry_matches_and_walls_are_lethal() -> None:
    data = np.zeros((20, 30), np.int8)
    data[0, :] = 100
    data[5:8, 5:8] = -1
    saved = OccupancyMap(data, 0.05, (-1.0, -0.5, 0.0))
    cost = np.where(data == 100, 100, 0).astype(np.int8)
    msg = m.OccupancyGrid(resolution=0.05, width=30, height=20, origin=m.Pose2D(x=-1.0, y=-0.5),
                          data=cost.tobytes())
    assert costmap_follows(msg, saved) == ""
    cost[0, 3] = 99
    assert "1 occupied map cells" in costmap_follows(msgspec.structs.replace(msg, data=cost.tobytes()), saved)
    other = m.OccupancyGrid(resolution=0.05, width=31, height=20, origin=m.Pose2D(x=-1.0, y=-0.5),
                            data=np.zeros(620, np.int8).tobytes())
    assert "31 x 20" in costmap_follows(other, saved)


def test_summary_table_means_over_reached_goals() -> None:
    runs = [{"run": r, "goals": [
        {"id": "1", "target": [3.0, 0.1, 1.57], "reached": True, "final": [0, 0, 0], "error": [0.01 * r, -0.02, 0.0],
         "time_s": 10.0 * r},
        {"id": "2", "target": [3.0, 3.5, 0.0], "reached": r == 1, "final": [0, 0, 0], "error": [0.03, 0.0, 0.01],
         "time_s": 5.0},
    ]} for r in (1, 2)]
    rows = summarize(runs)
    assert rows[0]["reached"] == 2 and rows[0]["total"] == 2
    assert rows[0]["mean_error"] == pytest.approx([0.015, -0.02, 0.0])
    assert rows[0]["mean_time_s"] == pytest.approx(15.0)
    assert rows[1]["reached"] == 1 and rows[1]["mean_error"] == pytest.approx([0.03, 0.0, 0.01])
    table = format_table(rows)
    assert "(3.00, 0.10, 1.57)" in table and "2/2" in table and "1/2" in table and "+0.015" in table


def test_plots_are_written(tmp_path: Path) -> None:
    t = np.linspace(0, 10, 50)
    trace = [(ti, 0.2 * ti, 0.1, 0.0, 0.2, 0.0, 0.01) for ti in t]
    leg = Leg(1, Goal("1", (2.0, 0.1, 0.0)), 0.0, plan=np.array([[0, 0, 0], [2, 0.1, 0]], dtype=float), trace=trace)
    grid = m.OccupancyGrid(resolution=0.1, width=40, height=20, origin=m.Pose2D(x=-1, y=-1),
                           data=np.zeros(800, dtype=np.int8).tobytes())
    files = draw_plots([leg], grid, tmp_path / "plots")
    assert len(files) == 2 and all(f.stat().st_size > 1000 for f in files)


@pytest.mark.parametrize("path", sorted((REPO / "scenarios").glob("*.toml")), ids=lambda p: p.name)
def test_every_shipped_scenario_loads_with_the_public_maps(path: Path, shared_dir: Path,
                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    """Shipped scenarios name public maps relative to a maps folder, never by a path outside the checkout."""
    if path.name == "suite.toml":
        return  # the suite has its own format (test_nav_robustness)
    assert "../" not in path.read_text(), f"{path.name} reaches outside the project"
    monkeypatch.delenv("ZAGV_MAPS_DIR", raising=False)
    sc = load_scenario(path, shared_dir / "data" / "maps")
    assert sc.goals or sc.robots


def test_a_map_found_nowhere_names_every_place_looked(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("ZAGV_MAPS_DIR", str(tmp_path / "maps"))
    p = write(tmp_path, 'map = "site/floor.yaml"\n[[goals]]\npose = [1.0, 0.0, 0.0]\n')
    with pytest.raises(ScenarioError) as err:
        load_scenario(p)
    assert str(tmp_path / "maps" / "site" / "floor.yaml") in str(err.value) and "--maps-dir" in str(err.value)
    (tmp_path / "maps" / "site").mkdir(parents=True)
    (tmp_path / "maps" / "site" / "floor.yaml").write_text("image: floor.pgm\n")
    assert load_scenario(p).map_yaml == str((tmp_path / "maps" / "site" / "floor.yaml").resolve())
