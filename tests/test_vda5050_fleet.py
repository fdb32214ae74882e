"""A third-party VDA 5050 master control drives several simulated robots with concurrent orders in one world.

npm ``vda-5050-lib``'s MasterController (``tests/vda5050_master``, run by node) masters every AGV of the fleet
through Debian's mosquitto; ``zagv up --robots N --vda5050`` runs a vda5050 service per robot, each publishing under
``uagv/v2/zagv/<robot id>/``. The master sees every AGV ONLINE, assigns each its order at once, and its
order-processed callbacks must report no error; the simulator's ground truth must show every node passed in order
within its allowed deviation and no contact. The routes cross, and nothing but each robot's own lidar, costmap and
collision monitor keeps them apart. The same run as a command: ``zagv scenario run scenarios/vda5050_crossing.toml``.
"""

from __future__ import annotations

import contextlib
import json
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from services.scenario.model import Scenario, load_scenario
from services.scenario.vda5050 import OrderNode, format_vda5050_fleet, order_message, run_orders, stack_args
from tests.support.hmi import full_stack_available as robot_available
from tests.support.stack import Stack
from tests.support.vda5050 import Master, Mosquitto, Recorder
from tests.support.waiting import wait_for_sync

pytestmark = [pytest.mark.integration, pytest.mark.slow,
              pytest.mark.skipif(not robot_available(), reason="needs the simulated robot services")]

REPO = Path(__file__).resolve().parents[1]

#: two robots whose short routes cross at (-1.0, -2.5): r1 eastwards 3 m, r2 northwards 4 m with a stop short of
#: r1's lane
TWO_CROSSING = """
world = "crossing"
speed = 1.0
name = "two-crossing"
[vda5050]
allowed_deviation_xy_m = 0.2
allowed_deviation_theta_rad = 0.2
[[robots]]
id = "r1"
start = [-2.5, -2.5, 0.0]
[[robots.goals]]
id = "r1-east"
pose = [0.5, -2.5, 0.0]
[[robots]]
id = "r2"
start = [-1.0, -4.5, 1.57]
[[robots.goals]]
id = "r2-mid"
pose = [-1.0, -2.9, 1.57]
[[robots.goals]]
id = "r2-north"
pose = [-1.0, -0.5, 1.57]
"""


class FleetRig:
    def __init__(self, sc: Scenario, stack: Stack, master: Master, recorder: Recorder) -> None:
        self.sc, self.stack, self.master, self.recorder = sc, stack, master, recorder


@contextlib.contextmanager
def fleet_rig(sc: Scenario, run_dir: Path) -> Iterator[FleetRig]:
    broker = Mosquitto(run_dir)
    recorder = Recorder(broker.port, "uagv/v2/zagv")  # every AGV's topics: uagv/v2/zagv/<serial>/#
    stack = Stack(run_dir, ["sim", "drive", "lidar", "safety", "localization", "nav", "vda5050"], speed=sc.speed,
                  world=sc.world or "crossing", robot_id=sc.robots[0].id, fleet_size=len(sc.robots),
                  extra_args=stack_args(sc, broker=("127.0.0.1", broker.port)))
    master = None
    try:
        master = Master(broker.port, [r.id for r in sc.robots])
        stack.start(ready_timeout_s=150.0 * len(sc.robots))
        yield FleetRig(sc, stack, master, recorder)
    finally:
        if master is not None:
            master.stop()
        recorder.stop()
        stack.stop()
        broker.stop()


def drive_and_check(rig: FleetRig, order_timeout_s: float) -> str:
    """The orders, concurrently; every order processed without error, every node passed, no contact."""
    started = time.monotonic()
    result = run_orders(rig.sc, rig.stack.session(), rig.master, order_timeout_s=order_timeout_s, progress=print)
    report = format_vda5050_fleet(result)
    print(report)
    print(f"wall time of the orders: {time.monotonic() - started:.1f} s")
    print(json.dumps(result.to_json()))
    ids = [r.id for r in rig.sc.robots]
    # every AGV came ONLINE under its own serialNumber, and its states arrived on its own topics
    for rid in ids:
        assert rig.master.find(lambda e, rid=rid: e["event"] == "connection" and e.get("serialNumber") == rid
                               and e["state"] == "ONLINE"), rid
        state = rig.master.last_state(rid)
        assert state is not None and state["orderId"] == f"{rig.sc.name}-{rid}", (rid, state)
    assert [r.id for r in result.robots] == ids
    for r in result.robots:
        assert r.processed and r.error is None and not r.by_cancelation, report
        assert r.traversed == [p.node_id for p in r.passes], report  # the master saw every node, in order
        assert r.nodes_passed == len(r.passes), report  # and the ground truth passed each within its deviation
    assert result.contacts == [], report
    assert result.ok, report
    # everything the vehicles published validates against the official schemas, and the master dropped nothing
    assert rig.recorder.count("state") > 4 * len(ids)
    assert not rig.recorder.invalid, rig.recorder.invalid[:5]
    assert not [line for line in rig.master.stderr if "Drop inbound message" in line]
    return report


def test_each_agv_of_a_fleet_has_its_own_topics_under_one_master(tmp_path: Path) -> None:
    """The make-test slice, without robots to drive: ``zagv up --sim --robots 2 --vda5050`` with only the vda5050
    services, on mosquitto. The master sees r1 and r2 ONLINE with a state each, on their own topics; an order to r2
    is answered by r2 alone (no map in this subset, so it is refused with noRouteError, as the standard says)."""
    broker = Mosquitto(tmp_path)
    recorder = Recorder(broker.port, "uagv/v2/zagv")
    stack = Stack(tmp_path, ["vda5050"], world="crossing", fleet_size=2,
                  extra_args=["--robots", "2", "--vda5050", "--no-embedded-broker", "--set",
                              f"vda5050.broker_port={broker.port}"])
    master = None
    try:
        master = Master(broker.port, ["r1", "r2"])
        stack.start(ready_timeout_s=120.0)
        for rid in ("r1", "r2"):
            master.wait(lambda e, rid=rid: e["event"] == "connection" and e.get("serialNumber") == rid
                        and e["state"] == "ONLINE", timeout_s=60, what=f"ONLINE of {rid}")
            master.wait(lambda e, rid=rid: e["event"] == "state" and e["serialNumber"] == rid, timeout_s=60,
                        what=f"a state of {rid}")
        own = {f"uagv/v2/zagv/{rid}/{topic}" for rid in ("r1", "r2") for topic in ("connection", "state", "factsheet")}
        wait_for_sync(lambda: recorder.topics() >= own, timeout_s=30,
                      message="not every AGV published on its own topics")
        order = order_message("to-r2", [OrderNode(n, x, 0.0, 0.0, 0.2, 0.2) for n, x in (("a", 0.0), ("b", 1.0))])
        mark = master.send({"cmd": "assign", "order": order, "serialNumber": "r2"})
        done = master.wait(lambda e: e["event"] == "orderProcessed" and e["serialNumber"] == "r2", timeout_s=30,
                           after=mark, what="r2's answer")
        assert done["error"] is not None and done["error"]["errorType"] == "noRouteError", done
        refs = {r["referenceKey"]: r["referenceValue"] for r in done["error"]["errorReferences"]}
        assert refs["orderId"] == "to-r2"
        assert not master.find(lambda e: e["event"] == "orderProcessed" and e["serialNumber"] == "r1")
        assert all(s.get("orderId", "") != "to-r2" for s in recorder.states() if s["serialNumber"] == "r1")
        assert not recorder.invalid, recorder.invalid[:5]
    finally:
        if master is not None:
            master.stop()
        recorder.stop()
        stack.stop()
        broker.stop()


@pytest.mark.long
def test_two_agvs_cross_under_one_master(tmp_path: Path) -> None:
    """Two robots, short crossing orders. r2 stops at a node just short of r1's lane first, as a master would stagger
    them: sent to cross at the same moment, the two stopped face to face 0.24 m apart, each held by its collision
    monitor, until nav gave both waypoints up with "localization lost for 30 s" (the other chassis filling the scan)."""
    f = tmp_path / "two.toml"
    f.write_text(TWO_CROSSING)
    sc = load_scenario(f)
    with fleet_rig(sc, tmp_path) as rig:
        drive_and_check(rig, order_timeout_s=180.0)


@pytest.mark.long
def test_three_agvs_cross_the_hall_under_one_master(tmp_path: Path) -> None:
    sc = load_scenario(REPO / "scenarios" / "vda5050_crossing.toml")
    with fleet_rig(sc, tmp_path) as rig:
        drive_and_check(rig, order_timeout_s=900.0)
