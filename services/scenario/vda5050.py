"""Fleet scenarios driven by a VDA 5050 master control: a ``[[robots]]`` scenario with a ``[vda5050]`` table.

    world = "crossing"
    [vda5050]
    allowed_deviation_xy_m = 0.2        # every node's allowedDeviationXy (m)
    allowed_deviation_theta_rad = 0.2   # every node's allowedDeviationTheta (rad)
    sequential = false                  # true: the master sends robot k's order once robot k-1's is processed
    [[robots]]
    id = "r1"
    start = [-6.5, -2.5, 0.0]
    [[robots.goals]]                    # the order's nodes after its first, at the start
    id = "mid"
    pose = [-2.0, -2.5, 0.0]

``zagv scenario run`` starts one ``zagv up --robots --vda5050`` stack (one vda5050 service per robot, serialNumber =
robot id, all on one MQTT broker: the embedded one, or ``--mqtt-broker HOST:PORT``) and the third-party master
control (npm ``vda-5050-lib``'s MasterController, ``services/scenario/vda5050_master.py``). Once the master sees every
AGV ONLINE with an initialized position at its start, it assigns every robot its order at once: one released node
per goal, with the goal's position and theta and the allowed deviations above. Nothing coordinates the robots but
what each sees with its lidar.

Judged per robot, from the simulator's ground truth: each node passed in order within its allowed deviation
(``judge_passes``: the first moment the true pose is within both deviations, after the previous node's), the order
time in sim seconds (assignment to the master's order-processed callback) and the callback's error; for the fleet,
contacts (robot-robot counted once per pair) and the closest approach of every pair (chassis edge to edge).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from proto import codec
from proto import messages as m
from proto.keys import Keys
from services.common.se2 import wrap_angle
from services.scenario.fleet import BLOCKED_GAP_M, closest_approach, merge_contacts
from services.scenario.model import Scenario, ScenarioRobot, Vda5050Orders

#: an AGV counts as at its start when its reported position is this close to it (m)
START_NEAR_M = 0.15


@dataclass(frozen=True)
class OrderNode:
    node_id: str
    x: float
    y: float
    theta: float
    dev_xy_m: float
    dev_theta_rad: float


def order_nodes(robot: ScenarioRobot, orders: Vda5050Orders) -> list[OrderNode]:
    """The robot's order: a first node at its start, then one node per goal (its id, position and theta)."""
    poses = [(f"{robot.id}-start", robot.start)] + [(g.id, g.pose) for g in robot.goals]
    return [OrderNode(nid, p[0], p[1], p[2], orders.allowed_deviation_xy_m, orders.allowed_deviation_theta_rad)
            for nid, p in poses]


def order_message(order_id: str, nodes: list[OrderNode], map_id: str = "map") -> dict[str, Any]:
    """A headerless VDA 5050 2.0 order: every node and edge released (node k has sequenceId 2k, edge k 2k+1)."""
    out_nodes = [{"nodeId": n.node_id, "sequenceId": 2 * k, "released": True, "actions": [],
                  "nodePosition": {"x": n.x, "y": n.y, "theta": n.theta, "mapId": map_id,
                                   "allowedDeviationXy": n.dev_xy_m, "allowedDeviationTheta": n.dev_theta_rad}}
                 for k, n in enumerate(nodes)]
    edges = [{"edgeId": f"{a.node_id}-{b.node_id}", "sequenceId": 2 * k + 1, "released": True,
              "startNodeId": a.node_id, "endNodeId": b.node_id, "actions": []}
             for k, (a, b) in enumerate(zip(nodes, nodes[1:]))]
    return {"orderId": order_id, "orderUpdateId": 0, "nodes": out_nodes, "edges": edges}


@dataclass
class NodePass:
    node_id: str
    passed: bool
    #: the least distance (m) between the true position and the node while passing it (or over the rest of the
    #: track when it was never passed)
    deviation_m: float
    #: |true heading - node theta| (rad) at the pass (where the distance was least when not passed)
    heading_error_rad: float
    #: sim time of the pass (the first moment within both deviations), None when not passed
    stamp: float | None


Sample = tuple[float, float, float, float]  # (sim stamp, x, y, theta)


def judge_passes(track: list[Sample], nodes: list[OrderNode]) -> list[NodePass]:
    """Each node in order: passed at the first sample (after the previous node's pass) within its allowed xy and
    theta deviations; its deviation is the least distance over the run of samples from there that stay within the
    xy deviation. A node not passed gets the least distance over the rest of the track, and so do the nodes after
    it (searched from the same place)."""
    out: list[NodePass] = []
    start = 0
    for n in nodes:
        def dist(s: Sample, n: OrderNode = n) -> float:
            return math.hypot(s[1] - n.x, s[2] - n.y)

        def heading(s: Sample, n: OrderNode = n) -> float:
            return abs(wrap_angle(s[3] - n.theta))

        hit = next((k for k in range(start, len(track))
                    if dist(track[k]) <= n.dev_xy_m and heading(track[k]) <= n.dev_theta_rad), None)
        if hit is None:
            rest = track[start:]
            best = min(rest, key=dist) if rest else None
            out.append(NodePass(n.node_id, False, round(dist(best), 4) if best else math.inf,
                                round(heading(best), 4) if best else math.inf, None))
            continue
        end = hit
        while end + 1 < len(track) and dist(track[end + 1]) <= n.dev_xy_m:
            end += 1
        best = min(track[hit:end + 1], key=dist)
        out.append(NodePass(n.node_id, True, round(dist(best), 4), round(heading(track[hit]), 4), track[hit][0]))
        start = hit
    return out


@dataclass
class RobotOrderResult:
    id: str
    order_id: str
    passes: list[NodePass]
    #: node ids the master's onNodeTraversed callback reported, in order
    traversed: list[str]
    order_time_s: float | None
    error: dict[str, Any] | None
    processed: bool
    by_cancelation: bool = False
    #: at the end of an order that is not ok: the robot whose chassis was nearest and the gap (m, edge to edge), to
    #: tell a robot blocked by another (and two blocked by each other: a deadlock) from one that failed alone
    nearest_robot: str | None = None
    nearest_gap_m: float | None = None

    @property
    def nodes_passed(self) -> int:
        """Nodes passed in order from the first (a node missed stops the count)."""
        count = 0
        for p in self.passes:
            if not p.passed:
                break
            count += 1
        return count

    @property
    def max_deviation_m(self) -> float:
        return max((p.deviation_m for p in self.passes), default=0.0)

    @property
    def ok(self) -> bool:
        return (self.processed and self.error is None and not self.by_cancelation
                and self.nodes_passed == len(self.passes)
                and self.traversed == [p.node_id for p in self.passes])

    def to_json(self) -> dict[str, Any]:
        return {"id": self.id, "order_id": self.order_id, "processed": self.processed, "error": self.error,
                "by_cancelation": self.by_cancelation, "order_time_s": self.order_time_s,
                "nodes_passed": self.nodes_passed, "nodes": len(self.passes),
                "max_deviation_m": self.max_deviation_m, "traversed": self.traversed,
                "passes": [p.__dict__ for p in self.passes], "nearest_robot": self.nearest_robot,
                "nearest_gap_m": self.nearest_gap_m}


@dataclass
class Vda5050FleetResult:
    robots: list[RobotOrderResult] = field(default_factory=list)
    contacts: list[dict] = field(default_factory=list)
    closest: dict[str, dict] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return bool(self.robots) and all(r.ok for r in self.robots) and not self.contacts

    def to_json(self) -> dict[str, Any]:
        return {"robots": [r.to_json() for r in self.robots], "contacts": self.contacts,
                "closest_approach": self.closest, "ok": self.ok}


def format_vda5050_fleet(result: Vda5050FleetResult) -> str:
    """Per robot: the order's outcome, nodes passed, max deviation and order time, then a line per node; then the
    fleet's contacts and closest approaches."""
    lines = []
    for r in result.robots:
        if not r.processed:
            outcome = "NOT processed"
        elif r.error is not None:
            outcome = f"processed with error {r.error.get('errorType')}: {r.error.get('errorDescription', '')}"
        elif r.by_cancelation:
            outcome = "canceled"
        else:
            outcome = "processed without error"
        took = f"{r.order_time_s:.1f} s (sim)" if r.order_time_s is not None else "-"
        lines.append(f"robot {r.id}: order {r.order_id} {outcome}; nodes passed {r.nodes_passed}/{len(r.passes)} in "
                     f"order within their allowed deviation (master traversed {len(r.traversed)}); max deviation "
                     f"{r.max_deviation_m:.3f} m; order time {took}")
        lines.append(f"  {'node':<14} {'passed':>6} {'deviation_m':>11} {'heading_rad':>11} {'at_s':>7}")
        for p in r.passes:
            at = f"{p.stamp:.1f}" if p.stamp is not None else "-"
            lines.append(f"  {p.node_id:<14} {'yes' if p.passed else 'NO':>6} {p.deviation_m:>11.3f} "
                         f"{p.heading_error_rad:>11.3f} {at:>7}")
        if not r.ok and r.nearest_robot is not None and r.nearest_gap_m is not None:
            lines.append(f"  at the end {r.nearest_robot} was {r.nearest_gap_m:.2f} m away (chassis edge to edge)"
                         + (": blocked by it?" if r.nearest_gap_m <= BLOCKED_GAP_M else ""))
    robot_contacts = [c for c in result.contacts if "wall" not in c["robots"]]
    lines.append(f"fleet: {sum(r.ok for r in result.robots)}/{len(result.robots)} orders processed without error "
                 f"with every node passed; contacts between robots {len(robot_contacts)}, with walls "
                 f"{len(result.contacts) - len(robot_contacts)}")
    if result.closest:
        lines.append("closest approach (chassis edge to edge): " + ", ".join(
            f"{pair} {v['gap_m']:.2f} m at {v['stamp']:.0f} s" for pair, v in result.closest.items()))
    for c in result.contacts:
        lines.append(f"contact at {c['stamp']:.1f} s: {' - '.join(c['robots'])}")
    return "\n".join(lines)


# --------------------------------------------------------------------------- the run (I/O)


class TruthTracker:
    """Every robot's ``sim/ground_truth``: (wall epoch, sample) tracks and contacts (rising edges of ``collided``)
    once ``watching``."""

    def __init__(self, session, robot_ids: list[str]) -> None:
        self._lock = threading.Lock()
        self.watching = False
        self.latest: dict[str, m.GroundTruth] = {}
        self.tracks: dict[str, list[tuple[float, Sample]]] = {rid: [] for rid in robot_ids}
        self.contacts: dict[str, list[tuple[float, str]]] = {rid: [] for rid in robot_ids}
        self._subs = [session.declare_subscriber(Keys(rid)("sim/ground_truth"), self._callback(rid))
                      for rid in robot_ids]

    def _callback(self, rid: str):
        key = Keys(rid)("sim/ground_truth")

        def on_sample(sample) -> None:
            msg = codec.decode_as(m.GroundTruth, sample.payload.to_bytes(), key)
            with self._lock:
                before = self.latest.get(rid)
                self.latest[rid] = msg
                if self.watching:
                    if msg.collided and not (before and before.collided):
                        self.contacts[rid].append((msg.stamp, msg.contact_with or "wall"))
                    self.tracks[rid].append((time.time(), (msg.stamp, msg.pose.x, msg.pose.y, msg.pose.theta)))
        return on_sample

    def stamp(self, rid: str) -> float:
        with self._lock:
            t = self.latest.get(rid)
            return t.stamp if t else 0.0

    def sim_at(self, rid: str, wall_epoch_s: float) -> float:
        """The sim stamp of the robot's sample received nearest to a wall time (epoch s)."""
        with self._lock:
            track = self.tracks[rid]
            if not track:
                return self.latest[rid].stamp if rid in self.latest else 0.0
            return min(track, key=lambda t: abs(t[0] - wall_epoch_s))[1][0]

    def nearest(self, rid: str, radius_m: float) -> tuple[str | None, float | None]:
        """The other robot whose chassis is nearest ``rid``'s now, and the gap |p - q| - 2 r (m)."""
        with self._lock:
            me = self.latest.get(rid)
            gaps = [(math.hypot(me.pose.x - o.pose.x, me.pose.y - o.pose.y) - 2 * radius_m, other)
                    for other, o in self.latest.items() if other != rid] if me else []
        if not gaps:
            return None, None
        gap, other = min(gaps)
        return other, round(gap, 3)

    def samples(self, rid: str) -> list[Sample]:
        with self._lock:
            return [s for _, s in self.tracks[rid]]

    def close(self) -> None:
        for s in self._subs:
            with contextlib.suppress(Exception):
                s.undeclare()


def _wait(pred, timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() > deadline:
            raise RuntimeError(f"{what} within {timeout_s:.0f} s")
        time.sleep(0.05)


def wait_fleet_online(master, robots: list[ScenarioRobot], timeout_s: float) -> None:
    """The master sees every AGV ONLINE and a state with its position initialized at its start."""
    def at_start(r: ScenarioRobot) -> bool:
        s = master.last_state(r.id)
        p = (s or {}).get("agvPosition") or {}
        return bool(p.get("positionInitialized")) and math.hypot(p["x"] - r.start[0], p["y"] - r.start[1]) \
            <= START_NEAR_M

    for r in robots:
        master.wait(lambda e, rid=r.id: e["event"] == "connection" and e.get("serialNumber") == rid
                    and e["state"] == "ONLINE", timeout_s=timeout_s, what=f"ONLINE of {r.id}")
    _wait(lambda: all(at_start(r) for r in robots), timeout_s,
          "not every AGV reported an initialized position at its start: " + ", ".join(
              f"{r.id} {((master.last_state(r.id) or {}).get('agvPosition'))}" for r in robots))


def run_orders(sc: Scenario, session, master, *, order_timeout_s: float = 900.0,
               ready_timeout_s: float = 240.0, progress=print) -> Vda5050FleetResult:
    """Assign every robot its order through ``master`` (a ``MasterProcess`` for every robot's serial number) and
    judge the run from the ground truth (see the module doc)."""
    orders = sc.vda5050 or Vda5050Orders()
    ids = [r.id for r in sc.robots]
    tracker = TruthTracker(session, ids)
    try:
        _wait(lambda: all(tracker.stamp(rid) > 0 for rid in ids), ready_timeout_s, "no ground truth of every robot")
        wait_fleet_online(master, sc.robots, ready_timeout_s)
        tracker.watching = True
        plans = {r.id: order_nodes(r, orders) for r in sc.robots}
        msgs = {rid: order_message(f"{sc.name}-{rid}", nodes) for rid, nodes in plans.items()}
        marks: dict[str, int] = {}
        assigned_sim: dict[str, float] = {}
        done: dict[str, dict] = {}
        progress(f"vda5050: {len(ids)} AGVs online at their starts; assigning "
                 f"{'one order after another' if orders.sequential else 'every order at once'}")
        for rid in ids:
            marks[rid] = master.send({"cmd": "assign", "order": msgs[rid], "serialNumber": rid})
            assigned_sim[rid] = tracker.stamp(rid)
            event = master.wait(lambda e, rid=rid: e["event"] in ("assigned", "assignFailed", "discarded")
                                and e.get("serialNumber") == rid, timeout_s=30, after=marks[rid],
                                what=f"assignment of {rid}'s order")
            if event["event"] != "assigned":
                raise RuntimeError(f"the master could not assign {rid}'s order: {event}")
            if orders.sequential:
                done[rid] = _processed(master, rid, msgs[rid], marks[rid], order_timeout_s, progress)
        for rid in ids:
            if rid not in done:
                done[rid] = _processed(master, rid, msgs[rid], marks[rid], order_timeout_s, progress)
        last = {rid: tracker.stamp(rid) for rid in ids}  # one more sim second of truth for every robot
        with contextlib.suppress(RuntimeError):
            _wait(lambda: all(tracker.stamp(rid) > last[rid] + 1.0 for rid in ids), 60, "no ground truth")
        tracker.watching = False
        result = Vda5050FleetResult()
        for rid in ids:
            event = done[rid]
            traversed = [e["nodeId"] for e in master.all(lambda e, rid=rid: e["event"] == "nodeTraversed"
                                                         and e.get("serialNumber") == rid, after=marks[rid])]
            processed = event.get("event") == "orderProcessed"
            took = tracker.sim_at(rid, event["t"] / 1000.0) - assigned_sim[rid] if processed else None
            result.robots.append(RobotOrderResult(
                rid, msgs[rid]["orderId"], judge_passes(tracker.samples(rid), plans[rid]), traversed,
                round(took, 2) if took is not None else None, event.get("error"), processed,
                bool(event.get("byCancelation"))))
        from services.common.robot import RobotSpec

        radius_m = RobotSpec().chassis_radius_m
        for r in result.robots:
            if not r.ok:
                r.nearest_robot, r.nearest_gap_m = tracker.nearest(r.id, radius_m)
        result.contacts = merge_contacts(tracker.contacts)
        result.closest = closest_approach(
            {rid: {round(s[0], 3): (s[1], s[2]) for s in tracker.samples(rid)} for rid in ids}, radius_m)
        return result
    finally:
        tracker.close()


def _processed(master, rid: str, order: dict, mark: int, timeout_s: float, progress) -> dict:
    """The master's orderProcessed event of ``rid``'s order, or a stand-in ``{"event": "timeout"}``."""
    try:
        event = master.wait(lambda e: e["event"] == "orderProcessed" and e.get("serialNumber") == rid
                            and e["orderId"] == order["orderId"], timeout_s=timeout_s, after=mark,
                            what=f"orderProcessed of {rid}")
    except AssertionError as exc:
        progress(f"vda5050: {rid}: {exc}")
        return {"event": "timeout", "t": time.time() * 1000.0, "error": None}
    why = f"error {event['error'].get('errorType')}" if event.get("error") else "no error"
    progress(f"vda5050: {rid}: order {order['orderId']} processed, {why}")
    return event


def stack_args(sc: Scenario, *, mqtt_port: int | None = None, broker: tuple[str, int] | None = None) -> list[str]:
    """``zagv up`` arguments of the fleet: its robots at their starts, a vda5050 service per robot on the embedded
    broker (``mqtt_port``) or on ``broker`` (host, port)."""
    extra = ["--headless", "--vda5050"]
    for r in sc.robots:
        extra += ["--robot", f"{r.id}:{r.start[0]!r},{r.start[1]!r},{r.start[2]!r}"]
    if broker is not None:
        extra += ["--no-embedded-broker", "--set", f"vda5050.broker_host=\"{broker[0]}\"",
                  "--set", f"vda5050.broker_port={broker[1]}"]
    elif mqtt_port is not None:
        extra += ["--mqtt-port", str(mqtt_port)]
    return extra


def parse_broker(text: str) -> tuple[str, int]:
    host, _, port = text.rpartition(":")
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"--mqtt-broker {text!r} must be HOST:PORT")
    return host, int(port)


def run_vda5050_fleet(sc: Scenario, args: argparse.Namespace) -> int:
    """``zagv scenario run`` of a ``[[robots]]`` scenario with ``[vda5050]``: exit 0 only when every order is
    processed without error with every node passed in order and there is no contact."""
    from services.common.ports import free_port
    from services.launch.stack_process import Stack
    from services.scenario.vda5050_master import MasterProcess, MasterUnavailable, install_master

    try:
        install_master()
        broker = parse_broker(args.mqtt_broker) if getattr(args, "mqtt_broker", None) else None
    except (MasterUnavailable, ValueError) as exc:
        print(f"zagv scenario: {exc}", file=sys.stderr)
        return 2
    mqtt_port = broker[1] if broker else free_port()
    run_dir = Path(args.run_dir or tempfile.mkdtemp(prefix="zagv-scenario-"))
    run_dir.mkdir(parents=True, exist_ok=True)
    extra = stack_args(sc, mqtt_port=None if broker else mqtt_port, broker=broker)
    extra += [a for s in args.set for a in ("--set", s)]
    stack = Stack(run_dir, None, world=sc.world or "corridor", map_yaml=sc.map_yaml, speed=sc.speed,
                  extra_args=extra, robot_id=sc.robots[0].id, fleet_size=len(sc.robots))
    print(f"zagv scenario: starting {len(sc.robots)} simulated robots with VDA 5050 interfaces (log "
          f"{run_dir / 'stack.log'})", flush=True)
    master = None
    try:
        stack.start(ready_timeout_s=120.0 * len(sc.robots))
        master = MasterProcess(mqtt_port, [r.id for r in sc.robots], broker_host=broker[0] if broker else "127.0.0.1")
        result = run_orders(sc, stack.session(), master, order_timeout_s=args.goal_timeout,
                            progress=lambda s: print(s, flush=True))
    except (AssertionError, RuntimeError) as exc:
        print(f"zagv scenario: {exc}", file=sys.stderr)
        return 1
    finally:
        if master is not None:
            master.stop()
        stack.stop()
    print(format_vda5050_fleet(result))
    if args.json:
        Path(args.json).write_text(json.dumps(result.to_json(), indent=2))
    return 0 if result.ok else 1
