"""The VDA 5050 2.0 vehicle-side state machine: orders, order updates, instant actions and the state report.

Pure and synchronous: the node hands in decoded MQTT payloads and the robot's signals (pose, velocity, drive, nav)
with the time, and gets back ``Effect`` values to carry out (drive the base nodes through nav's waypoints, stop,
set the initial pose, publish the factsheet). ``state()`` and ``visualization()`` build the message bodies; the
node adds the header (VDA 5050 §6.1).

Protocol rules implemented (VDA 5050 2.0, §6.6 order, §6.7 instant actions, §6.10 state):
- Only released (base) nodes are driven; horizon nodes are reported in ``nodeStates`` with ``released: false``.
- A node is traversed once the robot is within its ``allowedDeviationXy`` (and ``allowedDeviationTheta`` when the
  node has a theta) or nav reports the waypoint reached; it then leaves ``nodeStates``, becomes ``lastNodeId`` /
  ``lastNodeSequenceId``, and the edge leading to it leaves ``edgeStates``.
- Same ``orderId``: a lower ``orderUpdateId`` is stale (``orderUpdateError``), an equal one is a duplicate and
  ignored, a higher one must start with the current base's last node (its ``nodeId`` and ``sequenceId``), else
  ``orderUpdateError``. A new ``orderId`` while the base is still being driven must stitch onto the base's end the
  same way; otherwise it is refused with ``orderError``.
- A node that the map shows unreachable refuses the whole order with ``noRouteError`` and nothing moves.
- Every refusal names ``topic``, ``headerId``, ``orderId`` and ``orderUpdateId`` in ``errorReferences`` so that a
  master control can match it to what it sent.
- A message that is not JSON or violates the official schema is answered with a ``validationError``.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections import deque
from dataclasses import dataclass, field
from typing import Any

from services.common.se2 import wrap_angle
from services.vda5050.reachability import Reachability
from services.vda5050.schemas import validate

SUPPORTED_INSTANT_ACTIONS = ("cancelOrder", "startPause", "stopPause", "initPosition", "stateRequest",
                             "factsheetRequest")


# --------------------------------------------------------------------------- effects (what the node carries out)


@dataclass(frozen=True)
class Waypoint:
    """One base node to drive to: nav waypoint id, map pose (m, m, rad)."""

    id: str
    x: float
    y: float
    theta: float


@dataclass(frozen=True)
class DriveTo:
    """Drive through ``waypoints`` in order (replaces whatever nav is doing)."""

    sequence_id: str
    waypoints: tuple[Waypoint, ...]


@dataclass(frozen=True)
class StopDriving:
    """Cancel nav's goal or sequence: the robot stops."""

    reason: str


@dataclass(frozen=True)
class SetInitialPose:
    """Tell localization where the robot is (initPosition); report back with ``action_done``."""

    action_id: str
    x: float
    y: float
    theta: float


@dataclass(frozen=True)
class PublishFactsheet:
    """Publish the factsheet now (factsheetRequest)."""


@dataclass(frozen=True)
class PublishState:
    """Publish the state now even if nothing changed (stateRequest)."""


Effect = DriveTo | StopDriving | SetInitialPose | PublishFactsheet | PublishState


# --------------------------------------------------------------------------- order graph


@dataclass
class Node:
    node_id: str
    sequence_id: int
    released: bool
    position: dict[str, Any] | None
    description: str = ""

    def state(self) -> dict[str, Any]:
        out: dict[str, Any] = {"nodeId": self.node_id, "sequenceId": self.sequence_id, "released": self.released}
        if self.description:
            out["nodeDescription"] = self.description
        if self.position is not None:
            out["nodePosition"] = self.position
        return out


@dataclass
class Edge:
    edge_id: str
    sequence_id: int
    released: bool
    start_node_id: str
    end_node_id: str
    description: str = ""
    orientation: float | None = None

    def state(self) -> dict[str, Any]:
        out: dict[str, Any] = {"edgeId": self.edge_id, "sequenceId": self.sequence_id, "released": self.released}
        if self.description:
            out["edgeDescription"] = self.description
        return out


@dataclass
class ActionState:
    action_id: str
    action_type: str
    status: str  # WAITING | INITIALIZING | RUNNING | FINISHED | FAILED
    description: str = ""
    result: str = ""

    def state(self) -> dict[str, Any]:
        out: dict[str, Any] = {"actionId": self.action_id, "actionType": self.action_type,
                               "actionStatus": self.status}
        if self.description:
            out["actionDescription"] = self.description
        if self.result:
            out["resultDescription"] = self.result
        return out


@dataclass
class VehicleSettings:
    """What the state machine needs of the configuration."""

    manufacturer: str = "zagv"
    serial_number: str = "r1"
    map_id: str = "map"
    default_deviation_xy_m: float = 0.1
    default_deviation_theta_rad: float = 0.1
    driving_speed_mps: float = 0.01
    driving_turn_radps: float = 0.02
    battery_empty_v: float = 44.0
    battery_full_v: float = 52.0
    max_message_errors: int = 20
    clearance_m: float = 0.63


class OrderRejected(Exception):
    """An order or order update that cannot be taken: VDA 5050 ``errorType`` and a description."""

    def __init__(self, error_type: str, description: str, **refs: str) -> None:
        super().__init__(description)
        self.error_type = error_type
        self.description = description
        self.refs = refs


def _error(error_type: str, level: str, description: str, refs: dict[str, Any]) -> dict[str, Any]:
    return {"errorType": error_type, "errorLevel": level, "errorDescription": description,
            "errorReferences": [{"referenceKey": k, "referenceValue": str(v)} for k, v in refs.items()]}


def reported_angle(theta_rad: float) -> float:
    """An angle in (-pi, pi] rounded to 0.1 mrad for state and visualization, kept within the schemas' [-pi, pi]
    (-3.14159 alone would round to -3.1416, below the minimum -3.14159265359)."""
    return min(math.pi, max(-math.pi, round(theta_rad, 4)))


def payload_digest(payload: bytes) -> str:
    """The reference of a received payload in errors: the first 16 hex digits of its SHA-256."""
    return hashlib.sha256(payload).hexdigest()[:16]


@dataclass
class Signals:
    """The robot's latest signals as the node last reported them."""

    pose: tuple[float, float, float] | None = None
    localization_state: str = "localizing"
    match_score: float = 0.0
    spread_m: float = 0.0
    velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)
    estopped: bool = False
    drive_fault: str = ""
    drive_enabled: bool = False
    battery_v: float | None = None
    nav_error: str = ""


class Vehicle:
    """One AGV's VDA 5050 state (module docstring)."""

    def __init__(self, settings: VehicleSettings) -> None:
        self.s = settings
        self.signals = Signals()
        self.order_id = ""
        self.order_update_id = 0
        self.nodes: list[Node] = []  # not yet traversed, base then horizon
        self.edges: list[Edge] = []
        self.last_node_id = ""
        self.last_node_sequence_id = 0
        self.action_states: list[ActionState] = []
        self.paused = False
        self.message_errors: deque[dict[str, Any]] = deque(maxlen=settings.max_message_errors)
        self.order_errors: list[dict[str, Any]] = []
        self.reachability: Reachability | None = None
        self.driven_sequence = ""  # id of the nav sequence currently driving the base ("" when none)
        self._sequence_counter = 0
        self._waiting_to_stop: list[ActionState] = []  # cancelOrder / startPause finish once the robot stands
        self._canceling = False  # cancelOrder received: the order is dropped once the robot stands
        self.received = 0

    # ------------------------------------------------------------------ inputs: map and signals

    def set_map(self, cells: Any, resolution_m: float, origin_x_m: float, origin_y_m: float) -> None:
        self.reachability = Reachability(cells, resolution_m, origin_x_m, origin_y_m, self.s.clearance_m)

    def on_pose(self, x: float, y: float, theta: float) -> list[Effect]:
        if all(math.isfinite(v) for v in (x, y, theta)):
            self.signals.pose = (x, y, wrap_angle(theta))
        return self._progress()

    def on_localization(self, state: str, match_score: float, spread_m: float) -> None:
        self.signals.localization_state = state
        self.signals.match_score = min(1.0, max(0.0, match_score)) if math.isfinite(match_score) else 0.0
        self.signals.spread_m = spread_m if math.isfinite(spread_m) else 0.0

    def on_velocity(self, vx: float, vy: float, wz: float) -> list[Effect]:
        if all(math.isfinite(v) for v in (vx, vy, wz)):
            self.signals.velocity = (vx, vy, wz)
        return self._progress()

    def on_drive(self, estopped: bool, fault: str, enabled: bool, battery_v: float | None) -> list[Effect]:
        self.signals.estopped, self.signals.drive_fault, self.signals.drive_enabled = estopped, fault, enabled
        if battery_v is not None and math.isfinite(battery_v) and battery_v > 0:
            self.signals.battery_v = battery_v
        return []

    def on_waypoint_reached(self, waypoint_id: str) -> list[Effect]:
        """nav reports a waypoint of the driven sequence reached: its node and every one before are traversed."""
        for k, node in enumerate(self.nodes):
            if self._waypoint_id(node) == waypoint_id:
                for _ in range(k + 1):
                    self._traverse(self.nodes[0])
                break
        return self._progress()

    def on_nav_failed(self, sequence_id: str, reason: str) -> list[Effect]:
        """nav gave up on (or refused) the driven sequence: the order stops where it is, with an error."""
        if sequence_id != self.driven_sequence or not sequence_id:
            return []
        self.driven_sequence = ""
        self.signals.nav_error = reason
        self.order_errors.append(_error("navigationError", "WARNING", f"nav could not drive the base: {reason}",
                                        {"orderId": self.order_id, "orderUpdateId": self.order_update_id}))
        return [StopDriving(f"nav failed: {reason}")]

    def action_done(self, action_id: str, ok: bool, result: str) -> None:
        """The outcome of an effect that stood for an action (initPosition)."""
        for a in self.action_states:
            if a.action_id == action_id:
                a.status = "FINISHED" if ok else "FAILED"
                a.result = result[:200]
                if not ok:
                    self.message_errors.append(_error("instantActionError", "WARNING", result,
                                                      {"topic": "instantActions", "actionId": action_id,
                                                       "actionType": a.action_type}))

    # ------------------------------------------------------------------ derived state

    @property
    def driving(self) -> bool:
        vx, vy, wz = self.signals.velocity
        return math.hypot(vx, vy) > self.s.driving_speed_mps or abs(wz) > self.s.driving_turn_radps

    def base_nodes(self) -> list[Node]:
        return [n for n in self.nodes if n.released]

    def has_base(self) -> bool:
        return any(n.released for n in self.nodes) or any(e.released for e in self.edges)

    def _base_end(self) -> tuple[str, int]:
        """(nodeId, sequenceId) of the last node of the current base (the last traversed when all are)."""
        base = self.base_nodes()
        if base:
            return base[-1].node_id, base[-1].sequence_id
        return self.last_node_id, self.last_node_sequence_id

    def _waypoint_id(self, node: Node) -> str:
        return f"{node.node_id}#{node.sequence_id}"

    def _deviation(self, node: Node) -> tuple[float, float]:
        p = node.position or {}
        dxy = float(p.get("allowedDeviationXy", 0.0)) or self.s.default_deviation_xy_m
        dth = float(p.get("allowedDeviationTheta", 0.0)) or self.s.default_deviation_theta_rad
        return dxy, dth

    def within(self, node: Node, pose: tuple[float, float, float]) -> bool:
        """Whether ``pose`` is on ``node`` within its allowed deviations."""
        p = node.position
        if p is None:
            return False
        dxy, dth = self._deviation(node)
        if math.hypot(pose[0] - p["x"], pose[1] - p["y"]) > dxy:
            return False
        return "theta" not in p or abs(wrap_angle(pose[2] - p["theta"])) <= dth

    # ------------------------------------------------------------------ order progress

    def _traverse(self, node: Node) -> None:
        self.nodes.remove(node)
        self.last_node_id, self.last_node_sequence_id = node.node_id, node.sequence_id
        self.edges = [e for e in self.edges if e.sequence_id > node.sequence_id]

    def _progress(self) -> list[Effect]:
        effects: list[Effect] = []
        pose = self.signals.pose
        if pose is not None and not self.paused and not self._canceling:
            while self.nodes and self.nodes[0].released and self.within(self.nodes[0], pose):
                self._traverse(self.nodes[0])
        if self.driven_sequence and not self.base_nodes():
            self.driven_sequence = ""  # the base is done; nav finishes its last fine approach on its own
        if self._waiting_to_stop and not self.driving:
            if self._canceling:  # VDA 5050 §6.7.1: stopped, the order's nodes and edges go with cancelOrder FINISHED
                self.nodes, self.edges = [], []
                self._canceling = False
            for a in self._waiting_to_stop:
                a.status = "FINISHED"
            self._waiting_to_stop.clear()
        return effects

    def _drive_base(self) -> list[Effect]:
        """Send the untraversed base nodes to nav (nothing when paused or when there are none)."""
        if self.paused:
            return []
        base = self.base_nodes()
        if not base:
            return []
        pose = self.signals.pose or (0.0, 0.0, 0.0)
        heading = pose[2]
        waypoints = []
        for node in base:
            p = node.position
            assert p is not None
            theta = p.get("theta")
            if theta is None:
                edge = next((e for e in self.edges if e.end_node_id == node.node_id
                             and e.sequence_id == node.sequence_id - 1), None)
                theta = edge.orientation if edge is not None and edge.orientation is not None else heading
            heading = float(theta)
            waypoints.append(Waypoint(self._waypoint_id(node), float(p["x"]), float(p["y"]), heading))
        self._sequence_counter += 1
        self.driven_sequence = f"vda5050-{self._sequence_counter}"
        return [DriveTo(self.driven_sequence, tuple(waypoints))]

    # ------------------------------------------------------------------ inbound messages

    def receive(self, topic: str, payload: bytes) -> list[Effect]:
        """Handle one MQTT payload on ``order`` or ``instantActions``."""
        self.received += 1
        refs: dict[str, Any] = {"topic": topic, "payloadSha256": payload_digest(payload)}
        try:
            message = json.loads(payload)
        except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
            self._validation_error(refs, f"not JSON: {exc}")
            return []
        if isinstance(message, dict) and isinstance(message.get("headerId"), int):
            refs["headerId"] = message["headerId"]
        problems = validate(topic, message)
        if problems:
            if isinstance(message, dict):
                for key in ("orderId", "orderUpdateId"):
                    if isinstance(message.get(key), (str, int)) and not isinstance(message.get(key), bool):
                        refs[key] = message[key]
            self._validation_error(refs, "; ".join(problems))
            return []
        if message["manufacturer"] != self.s.manufacturer or message["serialNumber"] != self.s.serial_number:
            self._validation_error(refs, f"addressed to {message['manufacturer']}/{message['serialNumber']}, "
                                         f"this is {self.s.manufacturer}/{self.s.serial_number}")
            return []
        if topic == "order":
            return self._order(message, refs)
        return self._instant_actions(message, refs)

    def _validation_error(self, refs: dict[str, Any], description: str) -> None:
        self.message_errors.append(_error("validationError", "WARNING", description[:500], refs))

    def _order(self, order: dict[str, Any], refs: dict[str, Any]) -> list[Effect]:
        refs = {**refs, "orderId": order["orderId"], "orderUpdateId": order["orderUpdateId"]}
        try:
            nodes, edges = self._parse_graph(order)
            if order["orderId"] == self.order_id:
                if order["orderUpdateId"] < self.order_update_id:
                    raise OrderRejected("orderUpdateError", f"stale order update: orderUpdateId "
                                        f"{order['orderUpdateId']} is below the current {self.order_update_id}")
                if order["orderUpdateId"] == self.order_update_id:
                    return []  # the same update again (VDA 5050 §6.6.3: discard it)
                self._check_stitch(nodes, "orderUpdateError")
            elif self._canceling:
                raise OrderRejected("orderError", "the previous order is being canceled; send the new one once "
                                    "cancelOrder is FINISHED")
            elif self.has_base():
                self._check_stitch(nodes, "orderError")
            self._check_reachable(nodes)
        except OrderRejected as exc:
            self.order_errors = [e for e in self.order_errors if e["errorType"] == "navigationError"]
            self.message_errors.append(_error(exc.error_type, "WARNING", exc.description, {**refs, **exc.refs}))
            return []
        return self._accept(order, nodes, edges)

    def _parse_graph(self, order: dict[str, Any]) -> tuple[list[Node], list[Edge]]:
        nodes = [Node(n["nodeId"], n["sequenceId"], n["released"], n.get("nodePosition"),
                      n.get("nodeDescription", "")) for n in order["nodes"]]
        edges = [Edge(e["edgeId"], e["sequenceId"], e["released"], e["startNodeId"], e["endNodeId"],
                      e.get("edgeDescription", ""), e.get("orientation")) for e in order["edges"]]
        if len(edges) != len(nodes) - 1:
            raise OrderRejected("orderError", f"{len(nodes)} nodes need {len(nodes) - 1} edges, got {len(edges)}")
        for k, node in enumerate(nodes):
            if k and node.sequence_id != nodes[k - 1].sequence_id + 2:
                raise OrderRejected("orderError", f"node {node.node_id}: sequenceId {node.sequence_id} does not "
                                    f"follow {nodes[k - 1].sequence_id} + 2", nodeId=node.node_id)
            if node.released and k and not nodes[k - 1].released:
                raise OrderRejected("orderError", f"released node {node.node_id} follows a horizon node",
                                    nodeId=node.node_id)
            if node.position is None:
                raise OrderRejected("orderError", f"node {node.node_id} has no nodePosition; this vehicle plans "
                                    "its own paths between positions", nodeId=node.node_id)
            if node.position["mapId"] != self.s.map_id:
                raise OrderRejected("orderError", f"node {node.node_id} is on map {node.position['mapId']!r}, the "
                                    f"vehicle is on {self.s.map_id!r}", nodeId=node.node_id)
        if not nodes[0].released:
            raise OrderRejected("orderError", "the first node is not released")
        for k, edge in enumerate(edges):
            a, b = nodes[k], nodes[k + 1]
            if (edge.sequence_id != a.sequence_id + 1 or edge.start_node_id != a.node_id
                    or edge.end_node_id != b.node_id):
                raise OrderRejected("orderError", f"edge {edge.edge_id} (sequenceId {edge.sequence_id}, "
                                    f"{edge.start_node_id} -> {edge.end_node_id}) does not join node {a.node_id} "
                                    f"({a.sequence_id}) to {b.node_id} ({b.sequence_id})", edgeId=edge.edge_id)
            if edge.released and not b.released:
                raise OrderRejected("orderError", f"released edge {edge.edge_id} ends at horizon node {b.node_id}",
                                    edgeId=edge.edge_id)
        for n in order["nodes"]:
            for action in n["actions"]:
                raise OrderRejected("orderError", f"node action {action['actionType']!r} is not supported by "
                                    "this vehicle", actionId=action["actionId"], nodeId=n["nodeId"])
        for e in order["edges"]:
            for action in e["actions"]:
                raise OrderRejected("orderError", f"edge action {action['actionType']!r} is not supported by "
                                    "this vehicle", actionId=action["actionId"], edgeId=e["edgeId"])
        return nodes, edges

    def _check_stitch(self, nodes: list[Node], error_type: str) -> None:
        end_id, end_seq = self._base_end()
        first = nodes[0]
        if (first.node_id, first.sequence_id) != (end_id, end_seq):
            raise OrderRejected(error_type, f"the update starts at node {first.node_id} (sequenceId "
                                f"{first.sequence_id}), not at the end of the current base, {end_id or 'none'} "
                                f"(sequenceId {end_seq})", nodeId=first.node_id)

    def _check_reachable(self, nodes: list[Node]) -> None:
        if self.reachability is None:
            raise OrderRejected("noRouteError", "no map yet: the vehicle cannot plan a route")
        pose = self.signals.pose
        if pose is None:
            raise OrderRejected("noRouteError", "the vehicle does not know where it is (no pose yet)")
        for node in nodes:
            p = node.position
            assert p is not None
            why = self.reachability.why_unreachable((pose[0], pose[1]), (p["x"], p["y"]))
            if why:
                raise OrderRejected("noRouteError", f"node {node.node_id}: {why}", nodeId=node.node_id)

    def _accept(self, order: dict[str, Any], nodes: list[Node], edges: list[Edge]) -> list[Effect]:
        new_order = order["orderId"] != self.order_id
        stitched = self.has_base()
        self.order_errors = []
        self.signals.nav_error = ""
        if new_order and not stitched:
            # a fresh order: actionStates of the previous one go (VDA 5050 §6.10.8, kept until a new order)
            self.action_states = [a for a in self.action_states if a.status not in ("FINISHED", "FAILED")]
        self.order_id, self.order_update_id = order["orderId"], order["orderUpdateId"]
        if stitched:
            # the first node is the base's last one, already in nodeStates: keep the current base, replace the rest
            keep_nodes = [n for n in self.nodes if n.released]
            keep_edges = [e for e in self.edges if e.released]
            self.nodes = keep_nodes + nodes[1:]
            self.edges = keep_edges + edges
        else:
            self.nodes, self.edges = nodes, edges
        self._progress()
        return self._drive_base()

    # ------------------------------------------------------------------ instant actions

    def _instant_actions(self, message: dict[str, Any], refs: dict[str, Any]) -> list[Effect]:
        effects: list[Effect] = []
        for action in message["instantActions"]:
            effects += self._instant_action(action, refs)
        return effects

    def _instant_action(self, action: dict[str, Any], refs: dict[str, Any]) -> list[Effect]:
        kind, action_id = action["actionType"], action["actionId"]
        arefs = {**refs, "actionId": action_id, "actionType": kind}
        if kind not in SUPPORTED_INSTANT_ACTIONS:
            self.message_errors.append(_error("instantActionError", "WARNING", f"instant action {kind!r} is not "
                                              f"supported; supported: {', '.join(SUPPORTED_INSTANT_ACTIONS)}",
                                              arefs))
            return []
        state = ActionState(action_id, kind, "RUNNING", action.get("actionDescription", ""))
        self.action_states = [a for a in self.action_states if a.action_id != action_id] + [state]
        params = {p["key"]: p["value"] for p in action.get("actionParameters", [])}
        if kind == "cancelOrder":
            if (not self.has_base() and not self.nodes) or self._canceling:
                state.status = "FAILED"
                state.result = "no order to cancel"
                self.message_errors.append(_error("noOrderToCancel", "WARNING", "cancelOrder without an active "
                                                  "order", arefs))
                return []
            self._canceling = True
            self.driven_sequence = ""
            self.paused = False
            self._waiting_to_stop.append(state)
            self._progress()
            return [StopDriving("cancelOrder")]
        if kind == "startPause":
            self.paused = True
            self.driven_sequence = ""
            self._waiting_to_stop.append(state)
            self._progress()
            return [StopDriving("startPause")]
        if kind == "stopPause":
            was = self.paused
            self.paused = False
            state.status = "FINISHED"
            return self._drive_base() if was else []
        if kind == "initPosition":
            try:
                x, y, theta = float(params["x"]), float(params["y"]), float(params["theta"])
                if not all(math.isfinite(v) for v in (x, y, theta)):
                    raise ValueError("x, y and theta must be finite")
                map_id = str(params.get("mapId", self.s.map_id))
                if map_id != self.s.map_id:
                    raise ValueError(f"mapId {map_id!r} is not the vehicle's map {self.s.map_id!r}")
            except (KeyError, TypeError, ValueError) as exc:
                state.status = "FAILED"
                state.result = f"bad parameters: {exc}"
                self.message_errors.append(_error("instantActionError", "WARNING", f"initPosition: {exc} "
                                                  "(needs x, y, theta, mapId)", arefs))
                return []
            if self.has_base():
                state.status = "FAILED"
                state.result = "refused while an order is being driven"
                self.message_errors.append(_error("instantActionError", "WARNING", "initPosition refused while an "
                                                  "order is being driven", arefs))
                return []
            if "lastNodeId" in params:
                self.last_node_id = str(params["lastNodeId"])
            return [SetInitialPose(action_id, x, y, theta)]
        if kind == "stateRequest":
            state.status = "FINISHED"
            return [PublishState()]
        state.status = "FINISHED"  # factsheetRequest
        return [PublishFactsheet()]

    # ------------------------------------------------------------------ outbound bodies

    def errors(self) -> list[dict[str, Any]]:
        out = list(self.message_errors) + list(self.order_errors)
        sig = self.signals
        if sig.estopped:
            out.append(_error("emergencyStop", "FATAL", "the drive is emergency-stopped (release it from the HMI "
                              "or the drive/release query)", {}))
        if sig.drive_fault:
            out.append(_error("driveFault", "FATAL", sig.drive_fault[:300], {}))
        if sig.localization_state == "lost":
            out.append(_error("localizationLost", "WARNING", f"the scans no longer fit the map (match score "
                              f"{sig.match_score:.2f})", {}))
        return out

    def battery_state(self) -> dict[str, Any]:
        v = self.signals.battery_v
        if v is None:
            return {"batteryCharge": 0.0, "charging": False}
        charge = 100.0 * (v - self.s.battery_empty_v) / (self.s.battery_full_v - self.s.battery_empty_v)
        return {"batteryCharge": round(min(100.0, max(0.0, charge)), 1), "batteryVoltage": round(v, 2),
                "charging": False}

    def agv_position(self) -> dict[str, Any] | None:
        pose = self.signals.pose
        if pose is None:
            return None
        sig = self.signals
        out = {"x": round(pose[0], 4), "y": round(pose[1], 4), "theta": reported_angle(pose[2]), "mapId": self.s.map_id,
               "positionInitialized": sig.localization_state != "localizing",
               "localizationScore": round(sig.match_score if sig.localization_state != "lost" else 0.0, 3)}
        if sig.spread_m > 0:
            out["deviationRange"] = round(sig.spread_m, 3)
        return out

    def velocity(self) -> dict[str, float]:
        vx, vy, wz = self.signals.velocity
        return {"vx": round(vx, 4), "vy": round(vy, 4), "omega": round(wz, 4)}

    def operating_mode(self) -> str:
        # AUTOMATIC when the drive takes commands; otherwise an operator is in charge (jog, disabled drive)
        return "AUTOMATIC" if self.signals.drive_enabled and not self.signals.estopped else "MANUAL"

    def state(self) -> dict[str, Any]:
        """The ``state`` body (VDA 5050 §6.10) without header."""
        body: dict[str, Any] = {
            "orderId": self.order_id,
            "orderUpdateId": self.order_update_id,
            "lastNodeId": self.last_node_id,
            "lastNodeSequenceId": self.last_node_sequence_id,
            "nodeStates": [n.state() for n in self.nodes],
            "edgeStates": [e.state() for e in self.edges],
            "driving": self.driving,
            "paused": self.paused,
            "newBaseRequest": self.has_base() and len(self.base_nodes()) <= 1 and any(not n.released
                                                                                    for n in self.nodes),
            "operatingMode": self.operating_mode(),
            "actionStates": [a.state() for a in self.action_states],
            "batteryState": self.battery_state(),
            "errors": self.errors(),
            "information": [],
            "safetyState": {"eStop": "REMOTE" if self.signals.estopped else "NONE", "fieldViolation": False},
            "velocity": self.velocity(),
        }
        position = self.agv_position()
        if position is not None:
            body["agvPosition"] = position
        return body

    def change_key(self) -> str:
        """What makes a state report due (VDA 5050 §6.10.1: on change): everything but pose, velocity and the
        battery's fine print (a whole percent of charge, or the voltage becoming known, counts)."""
        body = self.state()
        for k in ("agvPosition", "velocity"):
            body.pop(k, None)
        battery = body.pop("batteryState")
        body["battery"] = (round(battery["batteryCharge"]), "batteryVoltage" in battery)
        return json.dumps(body, sort_keys=True)

    def visualization(self) -> dict[str, Any]:
        body: dict[str, Any] = {"velocity": self.velocity()}
        position = self.agv_position()
        if position is not None:
            body["agvPosition"] = position
        return body


@dataclass
class Headers:
    """Per-topic header counters (VDA 5050 §6.1: headerId counts per topic, from 0)."""

    manufacturer: str
    serial_number: str
    version: str = "2.0.0"
    counters: dict[str, int] = field(default_factory=dict)

    def wrap(self, topic: str, body: dict[str, Any], timestamp: str) -> dict[str, Any]:
        header_id = self.counters.get(topic, 0)
        self.counters[topic] = header_id + 1
        return {"headerId": header_id, "timestamp": timestamp, "version": self.version,
                "manufacturer": self.manufacturer, "serialNumber": self.serial_number, **body}
