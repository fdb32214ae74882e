"""``zagv scenario``: the scenario file format, the Table 3 summary and the plots (no stack needed)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from proto import messages as m
from services.cli.scenario import Goal, Leg, ScenarioError, draw_plots, format_table, load_scenario, summarize, wrap

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
])
def test_bad_scenarios_name_the_problem(tmp_path: Path, text: str, needle: str) -> None:
    with pytest.raises(ScenarioError) as err:
        load_scenario(write(tmp_path, text))
    assert needle in str(err.value)


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


def test_wrap_is_minus_pi_exclusive() -> None:
    assert wrap(-math.pi) == pytest.approx(math.pi)
    assert wrap(2 * math.pi - 0.1) == pytest.approx(-0.1)


def test_plots_are_written(tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    t = np.linspace(0, 10, 50)
    trace = [(ti, 0.2 * ti, 0.1, 0.0, 0.2, 0.0, 0.01) for ti in t]
    leg = Leg(1, Goal("1", (2.0, 0.1, 0.0)), 0.0, plan=np.array([[0, 0, 0], [2, 0.1, 0]], dtype=float), trace=trace)
    grid = m.OccupancyGrid(resolution=0.1, width=40, height=20, origin=m.Pose2D(x=-1, y=-1),
                           data=np.zeros(800, dtype=np.int8).tobytes())
    files = draw_plots([leg], grid, tmp_path / "plots")
    assert len(files) == 2 and all(f.stat().st_size > 1000 for f in files)
