"""Several robots in one simulated world for ``zagv up``: robot ids, start poses and per-robot ports.

``zagv up --sim --robots N`` (or ``--robot ID[:X,Y,THETA]`` per robot, or a world with ``[[robots]]``) starts one
simulator for the whole world (one sim clock) and, per robot, a full stack under ``agv/<id>/...``: its own simulated
CAN bus with its own emulated RoboteQ nodes, its own emulated LMS111 port, drive, lidar, safety, localization, nav,
recorder (and the HMI, Foxglove bridge and VDA 5050 interface when asked for). Robot k (0-based) uses the base
ports plus k: CAN ``--can-port + k``, LMS111 ``--lidar-port + k``, HMI ``--http-port + k``, Foxglove
``--foxglove-port + k``; one Zenoh router and one MQTT broker serve every robot. Each robot keeps its state in
``<run folder>/<id>/``. Children are named ``<id>.<service>`` (``sim`` is one child for all robots).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

ROBOT_ARG = re.compile(r"^(?P<id>[^/*$?#:\s]+)(?::(?P<pose>[^:]+))?$")


@dataclass(frozen=True)
class RobotSlot:
    """One robot of a fleet: its id and start pose (None: placed by the simulator's rule, known once resolved)."""

    id: str
    start: tuple[float, float, float] | None = None


def parse_robot_arg(text: str) -> RobotSlot:
    """``ID`` or ``ID:X,Y,THETA`` (m, m, rad) -> RobotSlot; ValueError naming what is wrong."""
    m = ROBOT_ARG.match(text.strip())
    if not m:
        raise ValueError(f"--robot {text!r}: expected ID or ID:X,Y,THETA (an id without / * $ ? # : or spaces)")
    if m.group("pose") is None:
        return RobotSlot(m.group("id"))
    try:
        vals = tuple(float(v) for v in m.group("pose").split(","))
    except ValueError:
        raise ValueError(f"--robot {text!r}: the start must be three numbers X,Y,THETA") from None
    if len(vals) != 3 or not all(math.isfinite(v) for v in vals):
        raise ValueError(f"--robot {text!r}: the start must be three finite numbers X,Y,THETA")
    return RobotSlot(m.group("id"), (vals[0], vals[1], vals[2]))


def fleet_slots(count: int, explicit: list[RobotSlot], world_robots: list[tuple[str, tuple[float, float, float]]]
                ) -> list[RobotSlot]:
    """The robots to run: ``explicit`` ones (``--robot``) if any, else the world's ``[[robots]]``; topped up to
    ``count`` with ids ``r1``, ``r2``, ... not yet taken (no start: placed by the simulator's rule)."""
    slots = list(explicit) or [RobotSlot(rid, start) for rid, start in world_robots]
    ids = [s.id for s in slots]
    if len(set(ids)) != len(ids):
        raise ValueError(f"robot ids must be distinct, got {', '.join(ids)}")
    k = 1
    while len(slots) < count:
        rid = f"r{k}"
        if rid not in ids:
            slots.append(RobotSlot(rid))
            ids.append(rid)
        k += 1
    return slots


def resolve_starts(slots: list[RobotSlot], world: str, map_yaml: str | None, radius_m: float) -> list[RobotSlot]:
    """Every slot with a start pose: the given ones kept, the others placed as the simulator places them
    (``services.sim.fleet.start_poses``: free, spaced, nearest the world's start first)."""
    if all(s.start is not None for s in slots):
        return slots
    from services.common.world import load_world
    from services.sim.fleet import start_poses

    w = load_world(world, map_yaml or "")
    given = [s.start for s in slots if s.start is not None]
    placed = iter(start_poses(w, len(slots), radius_m, given)[len(given):])
    return [s if s.start is not None else RobotSlot(s.id, next(placed)) for s in slots]


def world_robots(world: str, map_yaml: str | None) -> list[tuple[str, tuple[float, float, float]]]:
    """A built-in world's ``[[robots]]`` (a ROS map has none)."""
    if map_yaml:
        return []
    from services.common.world import load_world

    return load_world(world, "").robots


def sim_robots_toml(slots: list[RobotSlot], can_channels: list[str], lidar_ports: list[int]) -> str:
    """The ``sim.robots`` value for ``--set``: a TOML array of inline tables (SimRobot)."""
    items = []
    for s, ch, port in zip(slots, can_channels, lidar_ports):
        start = "" if s.start is None else ", start_pose = [" + ", ".join(repr(float(v)) for v in s.start) + "]"
        items.append(f'{{id = "{s.id}", can_channel = "{ch}", lidar_port = {port}{start}}}')
    return "[" + ", ".join(items) + "]"
