"""Several simulated robots in one world: shared sim time, lidars that see each other, robot-robot contact.

Pure and synchronous, like ``Simulation``: ``Fleet`` holds one ``Simulation`` per robot (each with its own emulated
RoboteQ nodes, IMU and scan source) over one ``World`` and advances them together, so every robot lives on the one
sim clock. Each robot's chassis is a disc of its ``footprint_radius_m`` (the paper's chassis radius, 0.63 m):

- clearance: a robot's margin at (x, y) is the least of its margin to the world and, for every other robot j,
  ``|p - p_j| - r - r_j``; the physics refuses a step that deepens an overlap, as it does for walls, and latches
  ``collided`` on both robots of a contact, naming the other robot in ``contact_with`` (a wall contact names
  ``"wall"``);
- lidar: each scan source also ray-casts the other robots' discs at the moment the scan is taken (the LMS111
  emulator asks for ranges at the scan's sim time): a beam from the laser origin o along unit d hits the disc
  (c, r) at ``t = b - sqrt(b^2 - (|c - o|^2 - r^2))`` with ``b = d . (c - o)`` when the root is real and t > 0.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable

import msgspec
import numpy as np

from services.common.robot import RobotSpec
from services.common.world import World
from services.sim.config import SimConfig
from services.sim.scan_source import Body
from services.sim.simulation import Frame, Simulation

WALL = "wall"


class Fleet:
    """Robots ``ids`` in ``world``, started at ``starts`` (x, y, theta each); ``step()`` advances all of them."""

    def __init__(self, cfg: SimConfig, spec: RobotSpec, world: World, ids: list[str],
                 starts: list[tuple[float, float, float]]) -> None:
        if len(ids) != len(starts) or not ids:
            raise ValueError(f"one start pose per robot: {len(ids)} ids, {len(starts)} starts")
        if len(set(ids)) != len(ids):
            raise ValueError(f"robot ids must be distinct, got {ids}")
        self.world = world
        self.ids = list(ids)
        self.sims: dict[str, Simulation] = {}
        for k, (rid, start) in enumerate(zip(ids, starts)):
            # own noise streams per robot; the same physics and hardware settings
            robot_cfg = msgspec.structs.replace(cfg, start_pose=[float(v) for v in start], seed=cfg.seed + 101 * k)
            self.sims[rid] = Simulation(robot_cfg, spec, world)
        self.contact_with: dict[str, str] = {rid: "" for rid in ids}
        for rid, sim in self.sims.items():
            sim.robot.margin = self._margin_fn(rid)
            sim.scan_source.bodies = self._bodies_fn(rid)
        for rid in ids:  # a start overlapping a wall or another robot is reported at once
            self.sims[rid].robot.collided = self.nearest(rid)[1] < 0.0
            self._check_contact(rid)

    # ------------------------------------------------------------------ geometry

    def _margin_fn(self, rid: str) -> Callable[[float, float], float]:
        sim = self.sims[rid]
        world = self.world
        radius = sim.footprint_radius_m
        others = [self.sims[o] for o in self.ids if o != rid]

        def margin(x: float, y: float) -> float:
            m = world.clearance_m(x, y, exact_within_m=radius) - radius
            for o in others:
                r = o.robot
                m = min(m, math.hypot(x - r.x, y - r.y) - radius - o.footprint_radius_m)
            return m

        return margin

    def _bodies_fn(self, rid: str) -> Callable[[], list[Body]]:
        others = [self.sims[o] for o in self.ids if o != rid]
        return lambda: [Body(o.robot.x, o.robot.y, o.footprint_radius_m) for o in others]

    def nearest(self, rid: str) -> tuple[str, float]:
        """What is closest to robot ``rid``'s chassis: (``"wall"`` or a robot id, margin m; < 0 overlapping)."""
        sim = self.sims[rid]
        r = sim.robot
        best = (WALL, self.world.clearance_m(r.x, r.y) - sim.footprint_radius_m)
        for oid in self.ids:
            if oid == rid:
                continue
            o = self.sims[oid]
            d = math.hypot(r.x - o.robot.x, r.y - o.robot.y) - sim.footprint_radius_m - o.footprint_radius_m
            if d < best[1]:
                best = (oid, d)
        return best

    def _check_contact(self, rid: str) -> None:
        """Name what a robot touched when its ``collided`` latch is set (at most one step of travel away)."""
        robot = self.sims[rid].robot
        if robot.collided and not self.contact_with[rid]:
            what, _ = self.nearest(rid)
            self.contact_with[rid] = what
            if what != WALL:  # both robots of a contact report it
                other = self.sims[what].robot
                other.collided = True
                if not self.contact_with[what]:
                    self.contact_with[what] = rid

    # ------------------------------------------------------------------ time

    @property
    def now_s(self) -> float:
        return self.sims[self.ids[0]].now_s

    @property
    def dt(self) -> float:
        return self.sims[self.ids[0]].dt

    @property
    def steps(self) -> int:
        return self.sims[self.ids[0]].steps

    def step(self) -> dict[str, list[Frame]]:
        """Advance every robot one physics step (in id order); returns each robot's CAN frames of the step."""
        out = {rid: self.sims[rid].step() for rid in self.ids}
        for rid in self.ids:
            self._check_contact(rid)
        return out

    def teleport(self, rid: str, x: float, y: float, theta: float) -> bool:
        """Move robot ``rid`` (False for non-finite values); clears its contact latch, then re-checks it."""
        sim = self.sims[rid]
        if not sim.teleport(x, y, theta):
            return False
        self.contact_with[rid] = ""
        sim.robot.collided = self.nearest(rid)[1] < 0.0
        self._check_contact(rid)
        return True


def start_poses(world: World, n: int, radius_m: float, given: list[tuple[float, float, float]] | None = None, *,
                wall_margin_m: float = 0.3, spacing_m: float = 0.6) -> list[tuple[float, float, float]]:
    """``n`` start poses: the ``given`` ones first (a world's or scenario's ``[[robots]]``), then deterministic
    places for the rest: the free cells whose centre is at least ``radius_m + wall_margin_m`` from every wall,
    in the drivable region of the world's start pose (8-connected), nearest to that start first, each at least
    ``2 * radius_m + spacing_m`` from every robot already placed; headings are the start's.
    Raises ValueError when the world has no room for ``n`` robots."""
    from scipy import ndimage

    poses = list(given or [])[:n]
    if len(poses) >= n:
        return poses
    res = world.resolution_m
    padded = np.ones((world.shape[0] + 2, world.shape[1] + 2), dtype=bool)
    padded[1:-1, 1:-1] = world.solid
    clearance = ndimage.distance_transform_edt(~padded)[1:-1, 1:-1] * res - 0.5 * res
    drivable = clearance >= radius_m + wall_margin_m
    regions, _ = ndimage.label(drivable, structure=np.ones((3, 3), dtype=bool))
    sx, sy, sth = world.start_pose
    r0, c0 = world.cell_of(sx, sy)
    rows, cols = world.shape
    label = int(regions[r0, c0]) if 0 <= r0 < rows and 0 <= c0 < cols else 0
    if label == 0:  # the start itself is cramped: the largest drivable region
        counts = np.bincount(regions.ravel())
        counts[0] = 0
        label = int(counts.argmax())
    rr, cc = np.nonzero(regions == label)
    xs = world.origin_xy[0] + (cc + 0.5) * res
    ys = world.origin_xy[1] + (rr + 0.5) * res
    order = np.argsort(np.hypot(xs - sx, ys - sy), kind="stable")
    gap = 2.0 * radius_m + spacing_m
    # the world's start pose itself first when it is drivable (a lone robot starts there too)
    start_ok = label == (int(regions[r0, c0]) if 0 <= r0 < rows and 0 <= c0 < cols else 0)
    cells = ((round(float(xs[i]), 3), round(float(ys[i]), 3)) for i in order)
    candidates = itertools.chain([(sx, sy)] if start_ok else [], cells)
    for x, y in candidates:
        if all(math.hypot(x - p[0], y - p[1]) >= gap for p in poses):
            poses.append((x, y, sth))
            if len(poses) == n:
                return poses
    raise ValueError(f"world {world.name} has room for {len(poses)} robots of radius {radius_m} m "
                     f"({gap:.2f} m apart, {radius_m + wall_margin_m:.2f} m from walls), not {n}")
