"""Scenarios with several robots in one world: ``[[robots]]`` with per-robot goals, one table per robot.

    world = "crossing"                # or map = "..."; speed as for one robot
    [[robots]]
    id = "r1"
    start = [-6.0, -2.0, 0.0]
    start_after_s = 0.0               # optional: sim seconds after the start before its first goal is sent
    [[robots.goals]]
    pose = [6.0, -2.0, 0.0]
    id = "east"                       # optional

``zagv scenario run`` starts one ``zagv up --robots`` stack (one simulator and clock, a full stack per robot, the
robots at their starts), tells each robot's localization where it is, then drives every robot through its goals
at the same time (each robot's goals in order). Each goal is judged as for one robot (ground truth within the goal
tolerance). Other robots appear to each robot only through its lidar and costmap, as on a real site.

Contacts: every rising edge of a robot's ``collided`` in ``sim/ground_truth`` after the start is a contact, with a
wall or with the robot named in ``contact_with``; a contact between two robots is counted once for the pair.
Deadlocks are reported, not hidden: a goal that ends unreached while another robot's chassis is within
``BLOCKED_GAP_M`` of the robot's is ``blocked by`` that robot; two robots blocked by each other are a deadlock.
JSON: ``{"robots": [{"id", "start", "goals": [...as for one robot..., "nearest_robot", "nearest_robot_gap_m"]}],
"contacts": [{"stamp", "robots": [a, b] | [a, "wall"]}], "deadlocks": [...], "blocked": [...]}``.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import sys
import tempfile
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

from proto import messages as m
from proto.keys import Keys
from services.common.query import QueryError
from services.scenario.client import Client
from services.scenario.model import Scenario, ScenarioRobot
from services.scenario.report import format_table, leg_totals, summarize
from services.scenario.runner import place_robot, run_goal

#: a goal that ends unreached with another chassis this close (m, edge to edge) was blocked by that robot
BLOCKED_GAP_M = 1.5


class FleetClient(Client):
    """A robot's ``Client`` that also records every contact (rising edge of ``collided``) once ``watching``."""

    def __init__(self, session, keys: Keys, loop: asyncio.AbstractEventLoop) -> None:
        self.contacts: list[tuple[float, str]] = []
        self.watching = False
        self.track: dict[float, tuple[float, float]] = {}  # sim stamp -> true (x, y) while watching
        super().__init__(session, keys, loop)

    def _on_truth(self, msg: m.GroundTruth) -> None:
        if self.watching:
            if msg.collided and not (self.truth and self.truth.collided):
                self.contacts.append((msg.stamp, msg.contact_with or "wall"))
            self.track[round(msg.stamp, 3)] = (msg.pose.x, msg.pose.y)
        super()._on_truth(msg)


@dataclass
class FleetResult:
    robots: list[dict] = field(default_factory=list)
    contacts: list[dict] = field(default_factory=list)
    blocked: list[str] = field(default_factory=list)
    deadlocks: list[str] = field(default_factory=list)
    #: per pair "a-b": the least edge-to-edge gap between the two chassis over the run (m) and when (sim s)
    closest: dict[str, dict] = field(default_factory=dict)

    def to_json(self) -> dict:
        return {"robots": self.robots, "contacts": self.contacts, "blocked": self.blocked,
                "deadlocks": self.deadlocks, "closest_approach": self.closest}


def merge_contacts(per_robot: dict[str, list[tuple[float, str]]], same_within_s: float = 1.0) -> list[dict]:
    """Contacts of every robot, a robot-robot contact once for the pair (both robots report it)."""
    out: list[dict] = []
    for rid, events in per_robot.items():
        for stamp, what in events:
            pair = sorted([rid, what]) if what != "wall" else [rid, "wall"]
            if what != "wall" and any(c["robots"] == pair and abs(c["stamp"] - stamp) <= same_within_s for c in out):
                continue
            out.append({"stamp": round(stamp, 3), "robots": pair})
    return sorted(out, key=lambda c: c["stamp"])


def closest_approach(tracks: dict[str, dict[float, tuple[float, float]]], radius_m: float) -> dict[str, dict]:
    """Per pair of robots, the least edge-to-edge gap |p_a - p_b| - 2 r (m) over the stamps both were seen at (the
    simulator publishes every robot's ground truth at the same stamps)."""
    out = {}
    ids = sorted(tracks)
    for i, a in enumerate(ids):
        for b in ids[i + 1:]:
            common = tracks[a].keys() & tracks[b].keys()
            if not common:
                continue
            t = min(common, key=lambda s: math.hypot(tracks[a][s][0] - tracks[b][s][0],
                                                     tracks[a][s][1] - tracks[b][s][1]))
            gap = math.hypot(tracks[a][t][0] - tracks[b][t][0], tracks[a][t][1] - tracks[b][t][1]) - 2 * radius_m
            out[f"{a}-{b}"] = {"gap_m": round(gap, 3), "stamp": t}
    return out


def blocked_and_deadlocks(robots: list[dict]) -> tuple[list[str], list[str]]:
    """From each robot's goal results (with ``nearest_robot`` / ``nearest_robot_gap_m`` of unreached goals): the
    goals blocked by another robot and the pairs of robots blocked by each other (deadlocks)."""
    blocked_by: dict[str, set[str]] = {}
    lines = []
    for r in robots:
        for g in r["goals"]:
            other, gap = g.get("nearest_robot"), g.get("nearest_robot_gap_m")
            if g["reached"] or other is None or gap is None or gap > BLOCKED_GAP_M:
                continue
            blocked_by.setdefault(r["id"], set()).add(other)
            lines.append(f"{r['id']} goal {g['id']} ({g.get('claimed', '')}: {g.get('nav_error', '')}) blocked by "
                         f"{other}, {gap:.2f} m apart")
    deadlocks = []
    for a, others in sorted(blocked_by.items()):
        for b in sorted(others):
            if a < b and a in blocked_by.get(b, set()):
                deadlocks.append(f"deadlock: {a} and {b} blocked each other (neither reached its goal)")
    return lines, deadlocks


def nearest_robot(c: Client, others: Mapping[str, Client], radius_m: float) -> tuple[str | None, float | None]:
    """The other robot whose chassis is nearest this one's (edge-to-edge gap m), from the ground truth."""
    if c.truth is None:
        return None, None
    best: tuple[str | None, float | None] = (None, None)
    for rid, o in others.items():
        if o is c or o.truth is None:
            continue
        gap = math.hypot(c.truth.pose.x - o.truth.pose.x, c.truth.pose.y - o.truth.pose.y) - 2 * radius_m
        if best[1] is None or gap < best[1]:
            best = (rid, round(gap, 3))
    return best


async def run_robot(robot: ScenarioRobot, c: Client, clients: Mapping[str, Client], t0: float, goal_timeout_s: float,
                    progress) -> dict:
    """Robot ``robot``'s goals in order, the first ``start_after_s`` after ``t0`` (sim s)."""
    from services.common.robot import RobotSpec

    spec = RobotSpec()
    solo = Scenario(goals=robot.goals)  # no dynamic obstacles: the other robots are the moving obstacles
    while c.sim_time < t0 + robot.start_after_s:
        await asyncio.sleep(0.05)
    goals = []
    for k, goal in enumerate(robot.goals, 1):
        res = await run_goal(c, solo, 1, k, goal, goal_timeout_s, None, spec.goal_xy_tolerance_m,
                             spec.goal_yaw_tolerance_rad)
        if not res["reached"]:
            res["nearest_robot"], res["nearest_robot_gap_m"] = nearest_robot(c, clients, spec.chassis_radius_m)
        goals.append(res)
        err = ", ".join(f"{v:+.3f}" if v is not None else "-" for v in res["error"])
        progress(f"scenario: {robot.id} goal {goal.id}: {'reached' if res['reached'] else 'NOT reached'} error "
                 f"{err} in {res['time_s']:.1f} s" + ("" if res["reached"] else
                                                        f" ({res['claimed']}: {res['nav_error']})"))
    return {"id": robot.id, "start": list(robot.start), "goals": goals}


async def run_fleet_scenario(sc: Scenario, session, *, goal_timeout_s: float, progress=print) -> FleetResult:
    loop = asyncio.get_running_loop()
    clients = {r.id: FleetClient(session, Keys(r.id), loop) for r in sc.robots}
    result = FleetResult()
    try:
        deadline = time.monotonic() + 240
        while any(c.truth is None or c.sim_time <= 0 for c in clients.values()):
            if time.monotonic() > deadline:
                missing = [rid for rid, c in clients.items() if c.truth is None]
                raise RuntimeError(f"no sim/ground_truth of {', '.join(missing)} within 240 s")
            await asyncio.sleep(0.05)
        await asyncio.gather(*(place_robot(clients[r.id], r.start) for r in sc.robots))
        for c in clients.values():
            c.watching = True
        t0 = max(c.sim_time for c in clients.values())
        progress(f"scenario: {len(sc.robots)} robots placed and localized at {t0:.1f} s (sim); driving")
        result.robots = list(await asyncio.gather(*(run_robot(r, clients[r.id], clients, t0, goal_timeout_s,
                                                              progress) for r in sc.robots)))
        await asyncio.sleep(0.2)  # the last ground truth of a contact at the very end
    finally:
        for c in clients.values():
            c.close()
    from services.common.robot import RobotSpec

    result.contacts = merge_contacts({rid: c.contacts for rid, c in clients.items()})
    result.closest = closest_approach({rid: c.track for rid, c in clients.items()}, RobotSpec().chassis_radius_m)
    result.blocked, result.deadlocks = blocked_and_deadlocks(result.robots)
    return result


def format_fleet(result: FleetResult) -> str:
    """One table per robot (as for one robot) and its totals line, then contacts, blocked goals and deadlocks."""
    lines = []
    for r in result.robots:
        runs = [{"run": 1, "goals": r["goals"]}]
        tot = leg_totals(runs)
        walls = sum(1 for c in result.contacts if c["robots"] == [r["id"], "wall"])
        with_robots = sum(1 for c in result.contacts if "wall" not in c["robots"] and r["id"] in c["robots"])
        lines += [f"robot {r['id']}", format_table(summarize(runs)),
                  f"{r['id']}: reached {tot['reached']}/{tot['goals']} goals within tolerance (ground truth); nav "
                  f"claimed {tot['claimed']}; contacts with walls {walls}, with robots {with_robots}; recoveries "
                  f"{tot['recoveries']}; {tot['time_per_metre_s']:.1f} s per metre driven", ""]
    robot_contacts = [c for c in result.contacts if "wall" not in c["robots"]]
    wall_contacts = [c for c in result.contacts if "wall" in c["robots"]]
    goals = [g for r in result.robots for g in r["goals"]]
    lines.append(f"fleet: {len(result.robots)} robots reached {sum(g['reached'] for g in goals)}/{len(goals)} goals; "
                 f"contacts between robots {len(robot_contacts)}, with walls {len(wall_contacts)}")
    if result.closest:
        lines.append("closest approach (chassis edge to edge): " + ", ".join(
            f"{pair} {v['gap_m']:.2f} m at {v['stamp']:.0f} s" for pair, v in result.closest.items()))
    for c in result.contacts:
        lines.append(f"contact at {c['stamp']:.1f} s: {' - '.join(c['robots'])}")
    lines += result.blocked + result.deadlocks
    return "\n".join(lines)


def run_fleet(sc: Scenario, args: argparse.Namespace) -> int:
    """``zagv scenario run`` of a scenario with ``[[robots]]``: exit 0 only when every goal is reached with no
    contact."""
    from services.launch.stack_process import Stack

    run_dir = Path(args.run_dir or tempfile.mkdtemp(prefix="zagv-scenario-"))
    run_dir.mkdir(parents=True, exist_ok=True)
    extra = ["--headless"]
    for r in sc.robots:
        extra += ["--robot", f"{r.id}:{r.start[0]!r},{r.start[1]!r},{r.start[2]!r}"]
    extra += [a for s in args.set for a in ("--set", s)]
    if args.start_seed is not None:
        extra += ["--start-seed", str(args.start_seed), "--start-delay-max", str(args.start_delay_max)]
    if getattr(args, "no_compose", False):
        extra += ["--no-compose"]
    stack = Stack(run_dir, None, world=sc.world or "corridor", map_yaml=sc.map_yaml, speed=sc.speed,
                  extra_args=extra, robot_id=sc.robots[0].id, fleet_size=len(sc.robots))
    print(f"zagv scenario: starting {len(sc.robots)} simulated robots (log {run_dir / 'stack.log'})", flush=True)
    try:
        stack.start(ready_timeout_s=120.0 * len(sc.robots))
        session = stack.session()
        result = asyncio.run(run_fleet_scenario(sc, session, goal_timeout_s=args.goal_timeout,
                                                progress=lambda s: print(s, flush=True)))
    except (AssertionError, RuntimeError, QueryError) as exc:
        print(f"zagv scenario: {exc}", file=sys.stderr)
        return 1
    finally:
        stack.stop()
    print(format_fleet(result))
    if args.json:
        Path(args.json).write_text(json.dumps(result.to_json(), indent=2))
    goals = [g for r in result.robots for g in r["goals"]]
    return 0 if goals and all(g["reached"] for g in goals) and not result.contacts else 1
