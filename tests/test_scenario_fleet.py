"""Multi-robot scenarios: the [[robots]] format, contacts counted per pair, blocked goals and deadlocks, and
``zagv scenario generate --robots``."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from services.common.world import World
from services.scenario.fleet import FleetResult, blocked_and_deadlocks, format_fleet, merge_contacts
from services.scenario.generate import generate_file
from services.scenario.model import ScenarioError, load_scenario

REPO = Path(__file__).resolve().parents[1]


def test_the_fleet_scenarios_load() -> None:
    sc = load_scenario(REPO / "scenarios" / "crossing_fleet.toml")
    assert [r.id for r in sc.robots] == ["r1", "r2", "r3"]
    assert [g.id for g in sc.robots[1].goals] == ["north", "home"]
    passage = load_scenario(REPO / "scenarios" / "passage_fleet.toml")
    assert passage.robots[1].start_after_s == 30.0


@pytest.mark.parametrize(("body", "message"), [
    ('[[robots]]\nid = "a"\nstart = [0, 0, 0]\n', r"robots\[1\] \(a\) has no \[\[robots.goals\]\]"),
    ('[[robots]]\nid = "a/b"\nstart = [0, 0, 0]\n[[robots.goals]]\npose = [1, 1, 0]\n', r"robots\[1\].id"),
    ('[[robots]]\nid = "a"\n[[robots.goals]]\npose = [1, 1, 0]\n', r"robots\[1\] \(a\) has no start"),
    ('[[robots]]\nid = "a"\nstart = [0, 0, 0]\nspeed = 2\n[[robots.goals]]\npose = [1, 1, 0]\n',
     r"robots\[1\]: unknown key\(s\) speed"),
    ('[[robots]]\nid = "a"\nstart = [0, 0, 0]\n[[robots.goals]]\npose = [1, 1]\n', r"robots\[1\].goals\[1\].pose"),
    ('[[robots]]\nid = "a"\nstart = [0, 0, 0]\n[[robots.goals]]\npose = [1, 1, 0]\n'
     '[[robots]]\nid = "a"\nstart = [3, 0, 0]\n[[robots.goals]]\npose = [1, 1, 0]\n', "distinct"),
    ('[[goals]]\npose = [1, 1, 0]\n[[robots]]\nid = "a"\nstart = [0, 0, 0]\n[[robots.goals]]\npose = [1, 1, 0]\n',
     "no top-level goals"),
])
def test_bad_robots_tables_are_named(tmp_path, body: str, message: str) -> None:
    f = tmp_path / "s.toml"
    f.write_text('world = "crossing"\n' + body)
    with pytest.raises(ScenarioError, match=message):
        load_scenario(f)


def test_a_contact_between_two_robots_counts_once_for_the_pair() -> None:
    contacts = merge_contacts({"r1": [(10.0, "r2"), (30.0, "wall")], "r2": [(10.02, "r1")], "r3": []})
    assert contacts == [{"stamp": 10.0, "robots": ["r1", "r2"]}, {"stamp": 30.0, "robots": ["r1", "wall"]}]
    # a second contact of the same pair later is another contact
    assert len(merge_contacts({"r1": [(10.0, "r2"), (50.0, "r2")], "r2": [(10.0, "r1"), (50.0, "r1")]})) == 2


def goal(gid: str, reached: bool, near: str | None = None, gap: float | None = None) -> dict:
    return {"id": gid, "target": [0, 0, 0], "reached": reached, "error": [0.0, 0.0, 0.0] if reached else [None] * 3,
            "time_s": 10.0, "claimed": "succeeded" if reached else "failed", "nav_error": "" if reached else "no path",
            "nearest_robot": near, "nearest_robot_gap_m": gap, "driven_m": 2.0}


def test_blocked_goals_and_deadlocks_are_reported() -> None:
    robots = [{"id": "r1", "goals": [goal("a", False, "r2", 0.3)]},
              {"id": "r2", "goals": [goal("b", False, "r1", 0.3)]},
              {"id": "r3", "goals": [goal("c", False, "r1", 5.0), goal("d", True)]}]
    blocked, deadlocks = blocked_and_deadlocks(robots)
    assert len(blocked) == 2 and "r1 goal a (failed: no path) blocked by r2, 0.30 m apart" in blocked
    assert deadlocks == ["deadlock: r1 and r2 blocked each other (neither reached its goal)"]
    # blocked by a robot that got through is no deadlock
    blocked, deadlocks = blocked_and_deadlocks([robots[0], {"id": "r2", "goals": [goal("b", True)]}])
    assert len(blocked) == 1 and deadlocks == []
    text = format_fleet(FleetResult(robots=robots, contacts=[], blocked=blocked, deadlocks=deadlocks))
    assert "robot r3" in text and "r3: reached 1/2 goals" in text and "contacts between robots 0" in text


def test_generate_places_several_robots_apart(tmp_path) -> None:
    out = generate_file(tmp_path / "g.toml", world="crossing", n_goals=3, seed=4, robots=3)
    sc = load_scenario(out)
    assert [r.id for r in sc.robots] == ["r1", "r2", "r3"] and all(len(r.goals) == 3 for r in sc.robots)
    world = World.load_builtin("crossing")
    assert sc.robots[0].start == world.start_pose
    places = {r.id: [r.start, *(g.pose for g in r.goals)] for r in sc.robots}
    for a in places:
        for b in places:
            if a < b:
                for p in places[a]:
                    for q in places[b]:
                        assert math.hypot(p[0] - q[0], p[1] - q[1]) >= 2 * 0.63 + 0.6 - 1e-6
        for p in places[a]:
            assert world.clearance_m(p[0], p[1]) >= 0.63 + 0.25 - 0.05
    assert out.read_text().startswith("# generated: 3 robots")


def test_closest_approach_per_pair() -> None:
    from services.scenario.fleet import closest_approach

    tracks = {"a": {0.0: (0.0, 0.0), 1.0: (1.0, 0.0), 2.0: (2.0, 0.0)},
              "b": {0.0: (5.0, 0.0), 1.0: (3.0, 0.0), 2.0: (4.0, 0.0)},
              "c": {5.0: (0.0, 0.0)}}
    out = closest_approach(tracks, 0.5)
    assert out == {"a-b": {"gap_m": 1.0, "stamp": 1.0}}  # 2 m apart at t = 1 and 2: the first; c never overlaps
