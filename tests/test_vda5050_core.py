"""The VDA 5050 vehicle state machine alone: orders, updates, instant actions, validation, and schema-valid output."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from services.common.robot import RobotSpec
from services.vda5050.config import Vda5050Config
from services.vda5050.core import (
    DriveTo,
    Headers,
    PublishFactsheet,
    SetInitialPose,
    StopDriving,
    Vehicle,
    VehicleSettings,
    payload_digest,
)
from services.vda5050.factsheet import factsheet
from services.vda5050.reachability import Reachability
from services.vda5050.schemas import validate

HEADER = {"timestamp": "2026-01-01T00:00:00.00Z", "version": "2.0.0", "manufacturer": "zagv", "serialNumber": "r1"}


def room(width_m: float = 10.0, height_m: float = 6.0, resolution_m: float = 0.05) -> np.ndarray:
    """A walled room with a closed box (free inside) in its north-east corner."""
    h, w = round(height_m / resolution_m), round(width_m / resolution_m)
    cells = np.zeros((h, w), dtype=np.int8)
    cells[0, :] = cells[-1, :] = cells[:, 0] = cells[:, -1] = 100
    cells[60:100, 140:190] = 100  # box walls x 7.0..9.5, y 3.0..5.0
    cells[62:98, 142:188] = 0  # its inside: free but enclosed
    return cells


def vehicle(pose: tuple[float, float, float] = (1.0, 1.0, 0.0)) -> Vehicle:
    v = Vehicle(VehicleSettings(clearance_m=0.63))
    v.set_map(room(), 0.05, 0.0, 0.0)
    v.on_pose(*pose)
    v.on_localization("tracking", 0.93, 0.02)
    v.on_drive(False, "", True, 48.0)
    return v


def msg(body: dict, header_id: int = 1) -> bytes:
    return json.dumps({"headerId": header_id, **HEADER, **body}).encode()


def order(order_id: str, update_id: int, points: list[tuple[str, float, float]], *, first_seq: int = 0,
          released: int | None = None, dev: float = 0.2) -> dict:
    released = len(points) if released is None else released
    nodes = [{"nodeId": n, "sequenceId": first_seq + 2 * k, "released": k < released, "actions": [],
              "nodePosition": {"x": x, "y": y, "mapId": "map", "allowedDeviationXy": dev}}
             for k, (n, x, y) in enumerate(points)]
    edges = [{"edgeId": f"{a['nodeId']}-{b['nodeId']}", "sequenceId": a["sequenceId"] + 1, "released": b["released"],
              "startNodeId": a["nodeId"], "endNodeId": b["nodeId"], "actions": []} for a, b in zip(nodes, nodes[1:])]
    return {"orderId": order_id, "orderUpdateId": update_id, "nodes": nodes, "edges": edges}


def instant(*actions: tuple[str, str], params: list | None = None) -> bytes:
    acts = [{"actionId": aid, "actionType": kind, "blockingType": "HARD", **({"actionParameters": params}
                                                                              if params else {})}
            for kind, aid in actions]
    return msg({"instantActions": acts})


def last_error(v: Vehicle) -> dict:
    return v.errors()[-1]


def refs(error: dict) -> dict:
    return {r["referenceKey"]: r["referenceValue"] for r in error["errorReferences"]}


def valid_state(v: Vehicle) -> dict:
    body = Headers("zagv", "r1").wrap("state", v.state(), HEADER["timestamp"])
    assert validate("state", body) == []
    return body


def test_order_drives_only_the_base_and_traverses_nodes_within_their_deviation() -> None:
    v = vehicle()
    out = v.receive("order", msg(order("o1", 0, [("a", 1.0, 1.0), ("b", 3.0, 1.0), ("c", 5.0, 1.0),
                                                  ("d", 5.0, 2.5)], released=3)))
    (drive,) = out
    assert isinstance(drive, DriveTo)
    assert [w.id for w in drive.waypoints] == ["b#2", "c#4"]  # a is traversed already; d is horizon
    assert v.last_node_id == "a" and v.last_node_sequence_id == 0
    s = valid_state(v)
    assert [(n["nodeId"], n["released"]) for n in s["nodeStates"]] == [("b", True), ("c", True), ("d", False)]
    assert [e["edgeId"] for e in s["edgeStates"]] == ["a-b", "b-c", "c-d"]
    v.on_pose(2.85, 1.1, 0.0)  # 0.18 m from b: inside its 0.2 m deviation
    assert v.last_node_id == "b" and [e.edge_id for e in v.edges] == ["b-c", "c-d"]
    v.on_pose(4.7, 1.0, 0.0)  # 0.3 m from c: not yet
    assert v.last_node_id == "b"
    v.on_waypoint_reached("c#4")  # nav settled on c
    assert v.last_node_id == "c" and [n.node_id for n in v.nodes] == ["d"] and not v.base_nodes()
    assert valid_state(v)["newBaseRequest"] is False


def test_order_update_stitches_and_stale_or_inconsistent_updates_are_rejected() -> None:
    v = vehicle()
    v.receive("order", msg(order("o1", 0, [("a", 1.0, 1.0), ("b", 3.0, 1.0)])))
    out = v.receive("order", msg(order("o1", 1, [("b", 3.0, 1.0), ("c", 5.0, 1.0), ("d", 5.0, 2.5)], first_seq=2,
                                       released=2)))
    assert [w.id for w in out[0].waypoints] == ["b#2", "c#4"]
    assert [(n.node_id, n.released) for n in v.nodes] == [("b", True), ("c", True), ("d", False)]
    assert v.order_update_id == 1
    assert v.receive("order", msg(order("o1", 1, [("b", 3.0, 1.0), ("c", 5.0, 1.0)], first_seq=2))) == []  # dup
    assert v.receive("order", msg(order("o1", 0, [("a", 1.0, 1.0), ("b", 3.0, 1.0)]), header_id=7)) == []
    e = last_error(v)
    assert e["errorType"] == "orderUpdateError" and "stale" in e["errorDescription"]
    assert refs(e) | {"payloadSha256": ""} == {"topic": "order", "headerId": "7", "orderId": "o1",
                                               "orderUpdateId": "0", "payloadSha256": ""}
    v.receive("order", msg(order("o1", 2, [("x", 5.0, 2.5), ("y", 6.0, 2.5)], first_seq=6)))
    assert last_error(v)["errorType"] == "orderUpdateError" and "not at the end of the current base" in \
        last_error(v)["errorDescription"]
    v.receive("order", msg(order("o2", 0, [("z", 1.0, 4.0), ("w", 2.0, 4.0)])))  # new order while driving
    assert last_error(v)["errorType"] == "orderError"
    assert v.order_id == "o1" and v.order_update_id == 1
    valid_state(v)


def test_unreachable_nodes_are_refused_with_no_route_and_nothing_is_driven() -> None:
    for x, y, why in [(8.2, 4.0, "no path"), (7.0, 3.0, "from an obstacle"), (20.0, 1.0, "outside the map")]:
        v = vehicle()
        assert v.receive("order", msg(order("o", 0, [("a", 1.0, 1.0), ("b", 3.0, 1.0), ("c", x, y)]))) == []
        e = last_error(v)
        assert e["errorType"] == "noRouteError" and why in e["errorDescription"], e
        assert refs(e)["nodeId"] == "c" and v.nodes == [] and v.order_id == ""


def test_graph_errors_and_unsupported_actions_are_order_errors() -> None:
    v = vehicle()
    bad_edge = order("o", 0, [("a", 1.0, 1.0), ("b", 3.0, 1.0)])
    bad_edge["edges"][0]["endNodeId"] = "zz"
    with_action = order("o", 0, [("a", 1.0, 1.0), ("b", 3.0, 1.0)])
    with_action["nodes"][1]["actions"] = [{"actionId": "p1", "actionType": "pick", "blockingType": "HARD"}]
    horizon_first = order("o", 0, [("a", 1.0, 1.0), ("b", 3.0, 1.0)], released=0)
    other_map = order("o", 0, [("a", 1.0, 1.0), ("b", 3.0, 1.0)])
    other_map["nodes"][1]["nodePosition"]["mapId"] = "hall-2"
    for o, text in [(bad_edge, "does not join"), (with_action, "not supported"), (horizon_first, "not released"),
                    (other_map, "hall-2")]:
        assert v.receive("order", msg(o)) == []
        assert last_error(v)["errorType"] == "orderError" and text in last_error(v)["errorDescription"]
    valid_state(v)


@pytest.mark.parametrize("payload", [b"\xff\xfe", b"{", b"[1, 2]", b"null", json.dumps({"headerId": "x"}).encode(),
                                     msg({"orderId": 5, "orderUpdateId": 0, "nodes": [], "edges": []})])
def test_malformed_messages_get_a_validation_error_naming_the_payload(payload: bytes) -> None:
    v = vehicle()
    for topic in ("order", "instantActions"):
        assert v.receive(topic, payload) == []
        e = last_error(v)
        assert e["errorType"] == "validationError" and refs(e)["payloadSha256"] == payload_digest(payload)
        assert refs(e)["topic"] == topic
    valid_state(v)


def test_wrong_addressee_is_a_validation_error() -> None:
    v = vehicle()
    body = json.loads(msg({"instantActions": []}))
    body["serialNumber"] = "r2"
    v.receive("instantActions", json.dumps(body).encode())
    assert "r2" in last_error(v)["errorDescription"]


def test_cancel_order_stops_and_finishes_once_the_robot_stands() -> None:
    v = vehicle()
    v.receive("order", msg(order("o1", 0, [("a", 1.0, 1.0), ("b", 5.0, 1.0)])))
    v.on_velocity(0.2, 0.0, 0.0)
    out = v.receive("instantActions", instant(("cancelOrder", "c1")))
    assert out == [StopDriving("cancelOrder")]
    s = valid_state(v)  # still moving: the order stays until the robot stands (VDA 5050 §6.7.1)
    assert [n["nodeId"] for n in s["nodeStates"]] == ["b"]
    assert s["actionStates"][-1] == {"actionId": "c1", "actionType": "cancelOrder", "actionStatus": "RUNNING"}
    v.on_pose(5.0, 1.0, 0.0)  # coasting onto b while canceling does not traverse it
    assert v.last_node_id == "a"
    v.on_velocity(0.0, 0.0, 0.0)
    s = valid_state(v)
    assert s["nodeStates"] == [] and s["edgeStates"] == [] and s["orderId"] == "o1"
    assert s["actionStates"][-1]["actionStatus"] == "FINISHED"
    v.receive("instantActions", instant(("cancelOrder", "c2")))  # nothing left to cancel
    assert last_error(v)["errorType"] == "noOrderToCancel"
    assert v.action_states[-1].status == "FAILED"


def test_pause_holds_the_base_and_resume_drives_the_rest() -> None:
    v = vehicle()
    v.receive("order", msg(order("o1", 0, [("a", 1.0, 1.0), ("b", 3.0, 1.0), ("c", 5.0, 1.0)])))
    assert v.receive("instantActions", instant(("startPause", "p1"))) == [StopDriving("startPause")]
    assert v.paused and v.action_states[-1].status == "FINISHED"  # standing still already
    v.on_pose(3.0, 1.0, 0.0)  # moved by hand while paused: nodes are not traversed
    assert v.last_node_id == "a"
    (drive,) = v.receive("instantActions", instant(("stopPause", "p2")))
    assert [w.id for w in drive.waypoints] == ["b#2", "c#4"]
    assert not v.paused and valid_state(v)["paused"] is False


def test_instant_actions_init_position_state_and_factsheet_requests_and_unsupported_ones() -> None:
    v = vehicle()
    params = [{"key": "x", "value": 2.0}, {"key": "y", "value": 1.5}, {"key": "theta", "value": 0.3},
              {"key": "mapId", "value": "map"}, {"key": "lastNodeId", "value": "home"}]
    out = v.receive("instantActions", instant(("initPosition", "i1"), params=params))
    assert out == [SetInitialPose("i1", 2.0, 1.5, 0.3)] and v.last_node_id == "home"
    v.action_done("i1", True, "ok")
    assert v.action_states[-1].status == "FINISHED"
    v.receive("instantActions", instant(("initPosition", "i2"), params=params[:1]))
    assert v.action_states[-1].status == "FAILED" and last_error(v)["errorType"] == "instantActionError"
    assert v.receive("instantActions", instant(("factsheetRequest", "f1"))) == [PublishFactsheet()]
    v.receive("instantActions", instant(("pick", "k1")))
    e = last_error(v)
    assert e["errorType"] == "instantActionError" and refs(e)["actionId"] == "k1" and "pick" in e["errorDescription"]
    assert all(a.action_id != "k1" for a in v.action_states)
    valid_state(v)


def test_state_reports_estop_battery_localization_and_position() -> None:
    v = vehicle()
    v.on_drive(True, "", True, 50.0)
    v.on_localization("lost", 0.2, 0.4)
    s = valid_state(v)
    assert s["safetyState"] == {"eStop": "REMOTE", "fieldViolation": False}
    assert {e["errorType"] for e in s["errors"]} >= {"emergencyStop", "localizationLost"}
    assert s["batteryState"] == {"batteryCharge": 75.0, "batteryVoltage": 50.0, "charging": False}
    assert s["agvPosition"]["localizationScore"] == 0.0 and s["agvPosition"]["deviationRange"] == 0.4
    assert s["operatingMode"] == "MANUAL"
    v.on_drive(False, "", True, 50.0)
    v.on_localization("tracking", 0.87, 0.02)
    s = valid_state(v)
    assert s["safetyState"]["eStop"] == "NONE" and s["agvPosition"]["localizationScore"] == 0.87
    assert s["operatingMode"] == "AUTOMATIC"


def test_message_errors_are_bounded() -> None:
    v = vehicle()
    for k in range(100):
        v.receive("order", f"junk {k}".encode())
    assert len(v.errors()) == v.s.max_message_errors


def test_reachability_of_a_closed_room() -> None:
    r = Reachability(room(), 0.05, 0.0, 0.0, clearance_m=0.63)
    assert r.regions == 2
    assert r.why_unreachable((1.0, 1.0), (5.0, 4.5)) == ""
    assert "no path" in r.why_unreachable((1.0, 1.0), (8.2, 4.0))


def test_factsheet_visualization_and_connection_validate() -> None:
    headers = Headers("zagv", "r1")
    sheet = headers.wrap("factsheet", factsheet(RobotSpec(), Vda5050Config()), HEADER["timestamp"])
    assert validate("factsheet", sheet) == []
    assert sheet["typeSpecification"]["agvKinematic"] == "OMNI"
    assert sheet["physicalParameters"]["width"] == pytest.approx(1.26)
    assert validate("visualization", headers.wrap("visualization", vehicle().visualization(), HEADER["timestamp"])) \
        == []
    connection = headers.wrap("connection", {"connectionState": "CONNECTIONBROKEN"}, HEADER["timestamp"])
    assert validate("connection", connection) == []
    assert headers.wrap("connection", {"connectionState": "ONLINE"}, HEADER["timestamp"])["headerId"] == 1


def test_state_is_due_on_order_or_safety_changes_but_not_on_motion_alone() -> None:
    v = Vehicle(VehicleSettings())
    key = v.change_key()
    v.on_pose(1.0, 1.0, 0.0)
    v.on_pose(1.1, 1.0, 0.0)
    assert v.change_key() == key  # position and velocity go out with visualization and the periodic state
    v.on_drive(False, "", False, 48.0)
    assert v.change_key() != key  # the battery voltage became known
    key = v.change_key()
    v.on_drive(True, "", False, 48.0)
    assert v.change_key() != key  # e-stop


@pytest.mark.parametrize("theta", [-3.14159, 3.14159, math.pi, -math.pi + 1e-9, 3.1415926])
def test_a_heading_next_to_pi_stays_within_the_schema_bounds(theta: float) -> None:
    # rounded to 0.1 mrad, -3.14159 rad became -3.1416, below the schemas' minimum (seen with a robot heading west)
    v = vehicle((2.0, 2.0, theta))
    headers = Headers("zagv", "r1")
    for topic, body in (("state", v.state()), ("visualization", v.visualization())):
        message = headers.wrap(topic, body, HEADER["timestamp"])
        assert validate(topic, message) == [], (topic, message["agvPosition"])
        assert abs(message["agvPosition"]["theta"]) <= math.pi
        assert message["agvPosition"]["theta"] == pytest.approx(theta, abs=1e-4)
