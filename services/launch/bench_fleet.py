"""Fleet benchmarks: three robots in the ``crossing`` world, each a full stack, all driving their crossing routes
(``scenarios/crossing_fleet.toml``: across the hall and back) while measuring.

- ``fleet.sim_speed_factor``: simulated seconds per wall second with the simulator free-running (speed 1000) and
  the three stacks keeping up as they can (the robots' services follow sim time, so this is the factor the machine
  holds for three robots).
- ``fleet.cpu_cores_per_robot``: the cores one robot's services (drive, lidar, safety, localization, nav, recorder;
  the mean of the three robots) need to run at 1x: their CPU seconds (/proc/<pid>/stat utime+stime) over the
  window divided by the sim seconds that passed in it (sim asked for 1x; on a machine that cannot hold 1x the sim
  slows down and so does the work, so CPU per sim second is the figure that does not depend on the load).
  ``fleet.rss_mb_per_robot``: their resident memory (VmRSS) at the end of the window. The one simulator and the
  robots' simulated CAN buses are shared hardware stand-ins: ``fleet.sim.cpu_cores`` / ``fleet.sim.rss_mb`` (the
  simulator plus every CAN bus process, per sim second likewise) are reported on their own rows, and
  ``fleet.achieved_speed_factor`` is the sim speed the window ran at.
"""

from __future__ import annotations

import asyncio
import tempfile
import time
from pathlib import Path

from proto import codec
from proto.keys import Keys
from proto.messages import Clock, Pose2D, Waypoint, WaypointsRequest
from services.common.bench import BenchRow
from services.common.query import QueryError, query
from services.launch.bench_stack import cpu_seconds, rss_mb
from services.launch.stack_process import Stack

WORLD = "crossing"
#: each robot's route: across the hall and back home (the crossing_fleet scenario's goals)
ROUTES = {
    "r1": [(6.0, -2.5, 0.0), (-6.5, -2.5, 0.0)],
    "r2": [(2.0, 4.0, 1.57), (-2.0, -4.5, 1.57)],
    "r3": [(-6.0, 2.5, 3.14), (6.5, 2.5, 3.14)],
}
ROBOT_SERVICES = ["drive", "lidar", "safety", "localization", "nav", "recorder"]


async def _start_routes(stack: Stack) -> None:
    session = stack.session()

    async def one(rid: str) -> None:
        request = WaypointsRequest(waypoints=[Waypoint(pose=Pose2D(x=x, y=y, theta=t), id=str(i + 1))
                                              for i, (x, y, t) in enumerate(ROUTES[rid])])
        deadline = time.monotonic() + 120.0
        while True:  # nav accepts goals once localization has given it a pose
            try:
                reply = await query(session, Keys(rid), "nav/waypoints", request, timeout_s=10.0)
                if reply.accepted:
                    return
                reason = reply.reason
            except QueryError as exc:
                reason = str(exc)
            if time.monotonic() > deadline:
                raise RuntimeError(f"{rid}'s nav refused the benchmark route: {reason}")
            await asyncio.sleep(0.5)

    await asyncio.gather(*(one(rid) for rid in ROUTES))


def _fleet_stack(tmp: str, speed: float) -> Stack:
    return Stack(Path(tmp), None, world=WORLD, speed=speed, extra_args=["--headless"], fleet_size=len(ROUTES))


def bench_fleet_footprint(window_s: float = 60.0) -> list[BenchRow]:
    with tempfile.TemporaryDirectory(prefix="zagv-bench-") as tmp:
        stack = _fleet_stack(tmp, 1.0)
        try:
            stack.start(ready_timeout_s=400.0)
            asyncio.run(_start_routes(stack))
            # each robot's processes once: composed (the default), lidar ... recorder share r1.components
            robot_pids = {rid: sorted({stack.pid(f"{rid}.{s}") for s in ROBOT_SERVICES}) for rid in ROUTES}
            shared_pids = [stack.pid("sim")] + [stack.pid(f"{rid}.canbus") for rid in ROUTES]
            every = [p for pids in robot_pids.values() for p in pids] + shared_pids
            stamps: list[float] = []
            sub = stack.session().declare_subscriber(Keys("r1")("clock"), lambda s: stamps.append(
                codec.decode_as(Clock, s.payload.to_bytes()).stamp))
            time.sleep(2.0)  # the first clock messages
            cpu0 = {p: cpu_seconds(p) for p in every}
            sim0 = stamps[-1] if stamps else 0.0
            t0 = time.monotonic()
            time.sleep(window_s)  # the measurement window
            elapsed = time.monotonic() - t0
            sim_elapsed = (stamps[-1] if stamps else 0.0) - sim0
            cores = {p: (cpu_seconds(p) - cpu0[p]) / max(sim_elapsed, 1e-9) for p in every}
            rss = {p: rss_mb(p) for p in every}
            sub.undeclare()
            if sim_elapsed <= 0.0:
                raise RuntimeError("the simulator's clock did not advance during the window")
        finally:
            stack.stop()
    n = len(robot_pids)
    return [
        BenchRow("fleet.cpu_cores_per_robot", sum(cores[p] for pids in robot_pids.values() for p in pids) / n,
                 "cores", "<= 0.5"),
        BenchRow("fleet.rss_mb_per_robot", sum(rss[p] for pids in robot_pids.values() for p in pids) / n, "MB",
                 "<= 600"),
        BenchRow("fleet.sim.cpu_cores", sum(cores[p] for p in shared_pids), "cores"),
        BenchRow("fleet.sim.rss_mb", sum(rss[p] for p in shared_pids), "MB"),
        BenchRow("fleet.achieved_speed_factor", sim_elapsed / elapsed, "x"),
    ]


def bench_fleet_sim_speed(window_s: float = 30.0) -> list[BenchRow]:
    """Sim seconds per wall second with three stacks up and driving, the simulator free-running."""
    with tempfile.TemporaryDirectory(prefix="zagv-bench-") as tmp:
        stack = _fleet_stack(tmp, 1000.0)
        try:
            stack.start(ready_timeout_s=400.0)
            asyncio.run(_start_routes(stack))
            session = stack.session()
            stamps: list[tuple[float, float]] = []
            sub = session.declare_subscriber(Keys("r1")("clock"), lambda s: stamps.append(
                (time.monotonic(), codec.decode_as(Clock, s.payload.to_bytes()).stamp)))
            time.sleep(window_s)  # the measurement window
            sub.undeclare()
        finally:
            stack.stop()
    if len(stamps) < 2:
        raise RuntimeError("no clock messages from the simulator")
    (w0, s0), (w1, s1) = stamps[0], stamps[-1]
    return [BenchRow("fleet.sim_speed_factor", (s1 - s0) / (w1 - w0), "x", ">= 1")]


BENCHES = [("fleet.sim_speed_factor", bench_fleet_sim_speed), ("fleet", bench_fleet_footprint)]
