"""Whole-stack benchmarks: footprint at 1x while the robot drives the corridor, and the sim's speed factor.

``stack.cpu_cores`` is the average number of cores used by the services over the measurement window, from
/proc/<pid>/stat utime+stime, in the topology ``zagv up`` starts by default: the drive, and the lidar, safety,
localization, nav, recorder and hmi_api composed in one process (``components``, services/launch/container.py).
The simulator and its CAN bus stand in for hardware and are not counted. ``stack.rss_mb`` is their total resident
memory (VmRSS) at the end of the window; each process's share is ``stack.<process>.cpu_cores`` / ``.rss_mb``.
``stack.pss_mb`` (for information) is their proportional set size at the same moment: pages shared between them
(the interpreter, numpy and zenoh libraries, zenoh's SHM pools) count once in total instead of once per process.
``stack.separate.*`` measures the same seven services each in a process of its own (``zagv up --no-compose``).
``sim.speed_factor`` is simulated seconds per wall second with the simulator free-running while the robot drives.
"""

from __future__ import annotations

import asyncio
import os
import tempfile
import time
from pathlib import Path

from proto import codec
from proto.messages import Clock, Pose2D, Waypoint, WaypointsRequest
from services.common.bench import BenchRow
from services.common.query import query
from services.launch.stack_process import Stack

#: corridor goals of the paper's Table 3, driven in order while measuring
CORRIDOR_ROUTE = [(3.0, 0.1, 1.57), (3.0, 3.5, 0.0), (13.6, 3.2, -1.0), (24.4, 3.5, 1.57)]
#: the services both footprints count (every one ``zagv up --sim`` starts but the simulator)
SERVICES = ["drive", "lidar", "safety", "localization", "nav", "recorder", "hmi_api"]
TICKS_PER_S = os.sysconf("SC_CLK_TCK")


def cpu_seconds(pid: int) -> float:
    """utime + stime of a process in s."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICKS_PER_S


def _proc_mb(path: str, field: str) -> float:
    """The ``field:`` line of a /proc file given in kB, in MB (0 when absent)."""
    with open(path) as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024.0
    return 0.0


def rss_mb(pid: int) -> float:
    return _proc_mb(f"/proc/{pid}/status", "VmRSS")


def pss_mb(pid: int) -> float:
    """Proportional set size (``Pss`` of /proc/<pid>/smaps_rollup): each shared page divided by its sharers."""
    return _proc_mb(f"/proc/{pid}/smaps_rollup", "Pss")


async def _start_route(stack: Stack) -> None:
    session = stack.session()
    request = WaypointsRequest(waypoints=[Waypoint(pose=Pose2D(x=x, y=y, theta=t), id=str(i + 1))
                                          for i, (x, y, t) in enumerate(CORRIDOR_ROUTE)])
    deadline = time.monotonic() + 60.0
    while True:  # nav accepts goals once localization has given it a pose
        reply = await query(session, stack.keys, "nav/waypoints", request, timeout_s=10.0)
        if reply.accepted:
            return
        if time.monotonic() > deadline:
            raise RuntimeError(f"nav refused the benchmark route: {reply.reason}")
        await asyncio.sleep(0.5)


def _running_services(stack: Stack) -> list[str]:
    return [s for s in SERVICES if f"[zagv.{s}]: started " in stack.output() or f"INFO {s}: started " in stack.output()]


def _measure(stack: Stack, children: list[str], window_s: float) -> tuple[dict, dict, dict]:
    """CPU cores, RSS and PSS (MB) of each supervised child process over ``window_s`` of wall time."""
    pids = {c: stack.pid(c) for c in children}
    cpu0 = {c: cpu_seconds(p) for c, p in pids.items()}
    t0 = time.monotonic()
    time.sleep(window_s)  # the measurement window
    elapsed = time.monotonic() - t0
    cores = {c: (cpu_seconds(p) - cpu0[c]) / elapsed for c, p in pids.items()}
    return cores, {c: rss_mb(p) for c, p in pids.items()}, {c: pss_mb(p) for c, p in pids.items()}


def bench_footprint(window_s: float = 60.0) -> list[BenchRow]:
    """``zagv up``'s default topology: the drive, and the other services composed in ``components``."""
    with tempfile.TemporaryDirectory(prefix="zagv-bench-") as tmp, Stack(Path(tmp), None, speed=1.0) as stack:
        services = _running_services(stack)
        if "nav" in services:
            asyncio.run(_start_route(stack))
        processes = sorted({stack.process_of(s) for s in services})
        cores, rss, pss = _measure(stack, processes, window_s)
    return _footprint_rows("stack", cores, rss, pss, "<= 0.30", "<= 450")


def bench_footprint_separate(window_s: float = 60.0) -> list[BenchRow]:
    """The same services each in a process of its own (``zagv up --no-compose``)."""
    with tempfile.TemporaryDirectory(prefix="zagv-bench-") as tmp, \
            Stack(Path(tmp), None, speed=1.0, extra_args=["--no-compose"]) as stack:
        services = _running_services(stack)
        if "nav" in services:
            asyncio.run(_start_route(stack))
        cores, rss, pss = _measure(stack, services, window_s)
    return _footprint_rows("stack.separate", cores, rss, pss, "information", "information")


def _footprint_rows(prefix: str, cores: dict, rss: dict, pss: dict, cpu_goal: str, rss_goal: str) -> list[BenchRow]:
    rows = [
        BenchRow(f"{prefix}.cpu_cores", sum(cores.values()), "cores", cpu_goal),
        BenchRow(f"{prefix}.rss_mb", sum(rss.values()), "MB", rss_goal),
        BenchRow(f"{prefix}.pss_mb", sum(pss.values()), "MB", "shared pages counted once (information)"),
    ]
    for c in cores:
        rows.append(BenchRow(f"{prefix}.{c}.cpu_cores", cores[c], "cores"))
        rows.append(BenchRow(f"{prefix}.{c}.rss_mb", rss[c], "MB"))
    return rows


def bench_sim_speed(window_s: float = 20.0) -> list[BenchRow]:
    """Sim seconds per wall second with the whole stack up and the robot driving, sim free-running."""
    with tempfile.TemporaryDirectory(prefix="zagv-bench-") as tmp, \
            Stack(Path(tmp), None, speed=1000.0) as stack:
        if "nav" in _running_services(stack):
            asyncio.run(_start_route(stack))
        session = stack.session()
        stamps: list[tuple[float, float]] = []
        sub = session.declare_subscriber(stack.keys("clock"), lambda s: stamps.append(
            (time.monotonic(), codec.decode_as(Clock, s.payload.to_bytes()).stamp)))
        time.sleep(window_s)  # the measurement window
        sub.undeclare()
    if len(stamps) < 2:
        raise RuntimeError("no clock messages from the simulator")
    (w0, s0), (w1, s1) = stamps[0], stamps[-1]
    return [BenchRow("sim.speed_factor", (s1 - s0) / (w1 - w0), "x", ">= 5")]


BENCHES = [("sim.speed_factor", bench_sim_speed), ("stack", bench_footprint),
           ("stack.separate", bench_footprint_separate)]
