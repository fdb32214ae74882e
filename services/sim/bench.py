"""Simulator benchmarks (``zagv bench --only sim``). Per-call figures are CPU time of the calling thread (medians),
so that other processes competing for the cores do not inflate them; the service row is wall time.

- ``sim.raycast_541_us``: one 541-beam, 270 degree scan (20 m range) in the corridor world, median over poses along
  the corridor and the hall (``_worst_us``: the slowest pose; ``sim.raycast_1081_us``: 0.25 degree scans).
- ``sim.step_us``: one 5 ms physics step with both controllers operational (TPDOs, heartbeats) while driving.
- ``sim.core_speed_factor``: sim seconds per CPU second of the core alone: 200 steps + 50 scans per sim second.
- ``sim.speed_factor_alone``: the simulator service in free-run (``speed_factor = 0``) with its router and CAN bus,
  measured from its ``clock`` topic over a few seconds (Zenoh publishing and CAN I/O included, no other service).
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from services.common.bench import BenchRow
from services.common.ports import free_port
from services.common.robot import RobotSpec
from services.common.world import World
from services.sim.config import SimConfig
from services.sim.simulation import Simulation

REPO_ROOT = Path(__file__).resolve().parents[2]
POSES = [(0.0, 0.0, 0.0), (3.0, 3.2, 0.0), (10.0, 3.2, 0.0), (15.0, 3.0, math.pi), (24.0, 6.5, 0.8),
         (23.5, 12.0, 1.57), (26.8, 6.6, 1.0), (13.6, 3.2, -1.0)]


def cpu_time_calls(fn, *, repeat: int = 200, warmup: int = 5, max_s: float = 5.0) -> np.ndarray:
    """CPU time (s) of this thread for each call of ``fn``: robust to other processes competing for the cores."""
    for _ in range(warmup):
        fn()
    out = []
    start = time.monotonic()
    for _ in range(repeat):
        t0 = time.thread_time()
        fn()
        out.append(time.thread_time() - t0)
        if time.monotonic() - start > max_s:
            break
    return np.asarray(out)


def _scan_medians(world: World, beams: int) -> list[float]:
    angles = np.linspace(-0.75 * math.pi, 0.75 * math.pi, beams)
    medians = []
    for x, y, th in POSES:
        rays = angles + th
        times = cpu_time_calls(lambda x=x, y=y, rays=rays: world.raycast(x, y, rays, 20.0), repeat=100, max_s=2.0)
        medians.append(float(np.median(times)))
    return medians


def raycast_rows() -> list[BenchRow]:
    world = World.load_builtin("corridor")
    m541 = _scan_medians(world, 541)
    m1081 = _scan_medians(world, 1081)
    return [BenchRow("sim.raycast_541_us", float(np.median(m541)) * 1e6, "us", "< 1000 (50 Hz x 5x on a core)"),
            BenchRow("sim.raycast_541_worst_us", max(m541) * 1e6, "us"),
            BenchRow("sim.raycast_1081_us", float(np.median(m1081)) * 1e6, "us", "0.25 deg at 25 Hz")]


def driving_sim() -> Simulation:
    sim = Simulation(SimConfig(world="corridor"), RobotSpec(), World.load_builtin("corridor"))
    sim.teleport(2.0, 3.2, 0.0)
    sim.boot()
    sim.on_can_frame(0x000, bytes([0x01, 0x00]))
    for n in (1, 2):
        sim.on_can_frame(0x600 + n, bytes([0x23, 0x00, 0x20, 0x01]) + (60).to_bytes(4, "little"))
    for _ in range(100):
        sim.step()
    return sim


def step_rows() -> list[BenchRow]:
    sim = driving_sim()
    step = float(np.median(cpu_time_calls(sim.step, repeat=2000, max_s=3.0)))
    angles = np.linspace(-0.75 * math.pi, 0.75 * math.pi, 541)
    scan = float(np.median(cpu_time_calls(lambda: sim.scan_source.laser_ranges(angles), repeat=200, max_s=3.0)))
    per_sim_second = 200 * step + 50 * scan
    return [BenchRow("sim.step_us", step * 1e6, "us", "< 200"),
            BenchRow("sim.core_speed_factor", 1.0 / per_sim_second, "x", ">= 5 (physics + 50 Hz scans)")]


def service_rows(seconds: float = 6.0) -> list[BenchRow]:
    from proto import codec
    from proto.keys import Keys
    from proto.messages import Clock
    from services.common.session import open_session
    from services.common.settings import ZenohSettings

    zenoh_port, can_port, lidar_port = free_port(), free_port(), free_port()
    run_dir = tempfile.mkdtemp(prefix="zagv-bench-sim-")
    argv = [sys.executable, "-m", "services.cli", "up", "--sim", "--only", "sim", "--headless", "--speed", "0",
            "--zenoh-port", str(zenoh_port), "--can-port", str(can_port), "--lidar-port", str(lidar_port),
            "--run-dir", run_dir]
    env = {**os.environ, "PYTHONPATH": str(REPO_ROOT)}
    proc = subprocess.Popen(argv, cwd=REPO_ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    stamps: list[tuple[float, float]] = []
    session = None
    try:
        deadline = time.monotonic() + 30.0
        while session is None and time.monotonic() < deadline:
            try:
                session = open_session(ZenohSettings(mode="client", connect=[f"tcp/127.0.0.1:{zenoh_port}"]))
            except Exception:
                time.sleep(0.2)
        if session is None:
            raise RuntimeError(f"no Zenoh router on port {zenoh_port} within 30 s (stack log in {run_dir})")
        sub = session.declare_subscriber(
            Keys()("clock"),
            lambda s: stamps.append((time.monotonic(), codec.decode_as(Clock, s.payload.to_bytes()).stamp)))
        deadline = time.monotonic() + 60.0  # the sim service starts in 2-5 s on a quiet machine, far later under load
        while not stamps and time.monotonic() < deadline:
            time.sleep(0.1)
        if not stamps:
            raise RuntimeError(f"the sim service published no clock within 60 s (stack log in {run_dir})")
        time.sleep(1.0)  # warm up
        first = stamps[-1]
        time.sleep(seconds)
        last = stamps[-1]
        sub.undeclare()
        factor = (last[1] - first[1]) / (last[0] - first[0])
        return [BenchRow("sim.speed_factor_alone", factor, "x", ">= 5 (free-run, sim service alone)")]
    finally:
        if session is not None:
            session.close()
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


def all_rows() -> list[BenchRow]:
    return raycast_rows() + step_rows() + service_rows()


BENCHES = [("sim", all_rows)]
