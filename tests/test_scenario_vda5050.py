"""VDA 5050 fleet scenarios without a stack: the [vda5050] table, the orders a master sends, how node passes are
judged from the ground truth, the report, and ``zagv up --robots N --vda5050`` giving each robot its serialNumber."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from services.scenario.model import ScenarioError, load_scenario
from services.scenario.vda5050 import (
    NodePass,
    OrderNode,
    RobotOrderResult,
    Vda5050FleetResult,
    format_vda5050_fleet,
    judge_passes,
    order_message,
    order_nodes,
    parse_broker,
    stack_args,
)
from services.vda5050.schemas import validate

REPO = Path(__file__).resolve().parents[1]


def test_the_vda5050_scenario_loads_and_its_orders_validate() -> None:
    sc = load_scenario(REPO / "scenarios" / "vda5050_crossing.toml")
    assert sc.vda5050 is not None and sc.vda5050.allowed_deviation_xy_m == 0.2 and not sc.vda5050.sequential
    assert [r.id for r in sc.robots] == ["r1", "r2", "r3"]
    nodes = order_nodes(sc.robots[1], sc.vda5050)
    assert [n.node_id for n in nodes] == ["r2-start", "r2-a", "r2-b", "r2-c"]
    assert (nodes[0].x, nodes[0].y) == (-2.0, -4.5) and nodes[-1].dev_xy_m == 0.2
    order = order_message("o1", nodes)
    assert [n["sequenceId"] for n in order["nodes"]] == [0, 2, 4, 6]
    assert [(e["sequenceId"], e["startNodeId"], e["endNodeId"]) for e in order["edges"]] == [
        (1, "r2-start", "r2-a"), (3, "r2-a", "r2-b"), (5, "r2-b", "r2-c")]
    # with the header the master adds, it is a valid VDA 5050 2.0 order
    header = {"headerId": 1, "timestamp": "2026-01-01T00:00:00.000Z", "version": "2.0.0", "manufacturer": "zagv",
              "serialNumber": "r2"}
    assert validate("order", {**header, **order}) == []
    # the stack: a robot per [[robots]] at its start, a vda5050 service each, the embedded broker or a given one
    args = stack_args(sc, mqtt_port=1999)
    assert "--vda5050" in args and args[args.index("--mqtt-port") + 1] == "1999"
    assert "r3:6.5,2.5,3.14" in args
    args = stack_args(sc, broker=("127.0.0.1", 1884))
    assert "--no-embedded-broker" in args and "vda5050.broker_port=1884" in args
    assert parse_broker("127.0.0.1:1884") == ("127.0.0.1", 1884)
    with pytest.raises(ValueError, match="HOST:PORT"):
        parse_broker("1884")


@pytest.mark.parametrize(("body", "message"), [
    ('[vda5050]\n[[goals]]\npose = [1, 1, 0]\n', r"\[vda5050\] orders need \[\[robots\]\]"),
    ('[vda5050]\nspeed = 1\n', r"vda5050: unknown key\(s\) speed"),
    ('[vda5050]\nallowed_deviation_xy_m = 0\n', r"vda5050.allowed_deviation_xy_m must be a number in \(0, 10\]"),
    ('[vda5050]\nsequential = "yes"\n', "vda5050.sequential must be true or false"),
])
def test_bad_vda5050_tables_are_named(tmp_path, body: str, message: str) -> None:
    f = tmp_path / "s.toml"
    robot = '[[robots]]\nid = "a"\nstart = [0, 0, 0]\n[[robots.goals]]\npose = [1, 1, 0]\n'
    f.write_text('world = "crossing"\n' + body + ("" if "[[goals]]" in body else robot))
    with pytest.raises(ScenarioError, match=message):
        load_scenario(f)


def node(nid: str, x: float, y: float, theta: float = 0.0, dev: float = 0.2) -> OrderNode:
    return OrderNode(nid, x, y, theta, dev, 0.2)


def test_node_passes_are_judged_in_order_within_the_deviation() -> None:
    # a straight run along x at y = 0.05, sampled every 0.1 m, stopping at x = 3
    track = [(0.5 * k, 0.1 * k, 0.05, 0.0) for k in range(31)]
    nodes = [node("a", 0.0, 0.0), node("b", 1.5, 0.0), node("c", 3.0, 0.0)]
    passes = judge_passes(track, nodes)
    assert [p.passed for p in passes] == [True, True, True]
    assert [p.deviation_m for p in passes] == pytest.approx([0.05, 0.05, 0.05])
    assert passes[1].stamp == pytest.approx(0.5 * 14)  # entered the 0.2 m disc at x = 1.4 (|(-0.1, 0.05)| < 0.2)
    # a node the robot only came within 0.3 m of is not passed, and its deviation says by how much it missed
    missed = judge_passes(track, [node("a", 0.0, 0.0), node("far", 1.5, 0.35)])
    assert not missed[1].passed and missed[1].deviation_m == pytest.approx(0.30) and missed[1].stamp is None
    # nodes passed in the wrong order: the second is judged only after the first one's pass
    backwards = judge_passes(track, [node("c", 3.0, 0.0), node("a", 0.0, 0.0)])
    assert [p.passed for p in backwards] == [True, False]
    # the heading counts too: at theta 0 the robot does not pass a node asking for theta pi/2
    turned = judge_passes(track, [node("c", 3.0, 0.0, theta=math.pi / 2)])
    assert not turned[0].passed and turned[0].heading_error_rad == pytest.approx(math.pi / 2, abs=1e-3)


def result(rid: str, passes: list[NodePass], traversed: list[str], error: dict | None = None) -> RobotOrderResult:
    return RobotOrderResult(rid, f"o-{rid}", passes, traversed, 42.5, error, True)


def test_the_report_gives_figures_per_robot_and_fails_on_any_miss() -> None:
    good = [NodePass("s", True, 0.01, 0.0, 0.0), NodePass("a", True, 0.04, 0.02, 20.0)]
    missed = [NodePass("s", True, 0.01, 0.0, 0.0), NodePass("a", False, 0.45, 0.1, None)]
    ok = Vda5050FleetResult([result("r1", good, ["s", "a"]), result("r2", good, ["s", "a"])],
                            closest={"r1-r2": {"gap_m": 0.42, "stamp": 31.0}})
    assert ok.ok
    text = format_vda5050_fleet(ok)
    assert "robot r1: order o-r1 processed without error; nodes passed 2/2" in text
    assert "max deviation 0.040 m; order time 42.5 s (sim)" in text
    assert "contacts between robots 0, with walls 0" in text and "r1-r2 0.42 m at 31 s" in text
    assert ok.to_json()["robots"][0]["max_deviation_m"] == 0.04
    # a missed node, an error from the master, a node the master never saw traversed, or a contact: not ok
    assert not Vda5050FleetResult([result("r1", missed, ["s"])]).ok
    assert "nodes passed 1/2" in format_vda5050_fleet(Vda5050FleetResult([result("r1", missed, ["s"])]))
    err = {"errorType": "navigationError", "errorDescription": "blocked"}
    assert not Vda5050FleetResult([result("r1", good, ["s", "a"], err)]).ok
    assert not Vda5050FleetResult([result("r1", good, ["s"])]).ok
    stuck = result("r1", missed, ["s"])
    stuck.processed, stuck.nearest_robot, stuck.nearest_gap_m = False, "r2", 0.2
    assert "NOT processed" in format_vda5050_fleet(Vda5050FleetResult([stuck]))
    assert "at the end r2 was 0.20 m away (chassis edge to edge): blocked by it?" in format_vda5050_fleet(
        Vda5050FleetResult([stuck]))
    contact = Vda5050FleetResult([result("r1", good, ["s", "a"])], contacts=[{"stamp": 3.0, "robots": ["r1", "r2"]}])
    assert not contact.ok and "contact at 3.0 s: r1 - r2" in format_vda5050_fleet(contact)


def test_each_robot_of_a_fleet_gets_its_own_serial_number(tmp_path) -> None:
    from services.launch.up import StackPlan, resolve_fleet

    plan = StackPlan(run_dir=str(tmp_path), headless=True, robot_count=3, vda5050=True, mqtt_port=1999)
    resolve_fleet(plan)
    specs = {c.name: c.argv for c in plan.children()}
    assert [n for n in specs if n.endswith("mqtt")] == ["mqtt"]  # one broker for the fleet
    for rid in ("r1", "r2", "r3"):
        argv = " ".join(specs[f"{rid}.vda5050"])
        assert f'vda5050.serial_number="{rid}"' in argv and "vda5050.broker_port=1999" in argv
    # a single robot keeps its configured (or robot-id) serial number
    single = StackPlan(run_dir=str(tmp_path), headless=True, vda5050=True)
    resolve_fleet(single)
    assert "serial_number" not in " ".join(next(c.argv for c in single.children() if c.name == "vda5050"))
    shared = StackPlan(run_dir=str(tmp_path), headless=True, robot_count=2, vda5050=True,
                       extra_sets=['vda5050.serial_number="agv"'])
    with pytest.raises(ValueError, match="cannot share one VDA 5050 serialNumber"):
        resolve_fleet(shared)
