"""Recording and replay on the corridor Table 3 run: the harness of the record/replay tests and their bench rows.

``record_corridor`` starts the simulated stack (AMCL seeded), runs ``zagv record`` as its own process while the
scenario runner sets the initial pose (inside the bag, so that a replay re-initialises the filter on the same scan)
and drives the Table 3 goals once, and keeps every scan, odom and map->odom payload that was published (so a test
can compare the bag with them). ``replay_into_localization`` starts localization alone (no sim, no
drive, on the replayed clock) and plays the bag's ``scan`` and ``odom`` into it with ``zagv replay``, collecting the
poses it publishes.

Rows: ``record.mb_per_min`` (bag MB per minute of robot time), ``record.cpu_cores`` (CPU of the ``zagv record``
process per second of robot time, i.e. cores at 1x), ``replay.speed_factor`` (bag seconds per wall second of
``zagv replay --rate 0`` with nothing listening).
"""

from __future__ import annotations

import asyncio
import os
import resource
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import zenoh

from proto import codec
from proto import messages as m
from services.common.bench import BenchRow
from services.common.se2 import compose
from services.launch.stack_process import REPO_ROOT, Stack

SCENARIO = REPO_ROOT / "scenarios" / "corridor_table3.toml"
RECORDED = ("scan", "odom", "tf/map_odom", "pose")
AMCL_SEED = 7
#: sim seconds the robot stands still at the start of the bag (a fresh localization settles in a few seconds at rest)
REST_BEFORE_DRIVING_S = 10.0
BLACKBOX_MINUTE_S = 60.0
#: covariance (x, y, theta; m^2, rad^2) of the initial pose set at the start of the bag (the scenario runner's)
INITIAL_COVARIANCE = [0.0025, 0.0, 0.0, 0.0, 0.0025, 0.0, 0.0, 0.0, 0.003]


@dataclass
class CorridorRecording:
    bag: Path
    published: dict[str, list[bytes]] = field(default_factory=dict)
    sim_s: float = 0.0
    record_cpu_s: float = 0.0
    goals_reached: int = 0
    goals: int = 0
    world_yaml: Path | None = None
    estop_s: float | None = None
    blackbox_dir: Path | None = None
    #: sim time at which each goal was sent (leg k runs from leg_starts_s[k] to the next; before the first: at rest)
    leg_starts_s: list[float] = field(default_factory=list)


def _env() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(REPO_ROOT), "PYTHONUNBUFFERED": "1", "ZAGV_PARENT_PID": str(os.getpid())}


def _children_cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def record_corridor(run_dir: Path, *, goals: int | None = None, speed: float = 3.0,
                    extra_args: list[str] | None = None, estop_at_s: float | None = None) -> CorridorRecording:
    """Drive the first ``goals`` Table 3 goals (all when None) once while ``zagv record`` records everything.

    With ``estop_at_s``, the recorder service (black box) runs too, and once the goals are done and the sim clock has
    passed ``estop_at_s`` the drive is e-stopped; the black box bag it leaves is waited for."""
    from services.scenario.model import load_scenario

    sc = load_scenario(SCENARIO)
    sc.repeats = 1
    if goals is not None:
        sc.goals = sc.goals[:goals]
        sc.dynamic_obstacles = [o for o in sc.dynamic_obstacles if o.during_goal <= goals]
    bag = run_dir / "corridor_bag"
    published: dict[str, list[bytes]] = {k: [] for k in RECORDED}
    lock = threading.Lock()
    args = ["--set", f"localization.random_seed={AMCL_SEED}", *(extra_args or [])]
    services = ["sim", "drive", "lidar", "localization", "nav"] + (["recorder"] if estop_at_s is not None else [])
    stack = Stack(run_dir / "stack", services, speed=speed, extra_args=args)
    estop_s = None
    (run_dir / "stack").mkdir(parents=True, exist_ok=True)
    # listen from the router's start, before any service publishes: the black box holds every message since the
    # recorder service started, and each one it holds must be compared with what was published
    with stack.start(ready_timeout_s=300.0, wait_ready=False):
        session = stack.session()

        def keep(name: str):
            def on_sample(sample: zenoh.Sample) -> None:
                with lock:
                    published[name].append(sample.payload.to_bytes())
            return on_sample

        subs = [session.declare_subscriber(stack.keys(k), keep(k)) for k in RECORDED]
        stack.wait_line(r"^zagv: ready", timeout_s=300.0)
        cpu0 = _children_cpu_s()
        rec = subprocess.Popen([sys.executable, "-m", "services.cli", "record", "--connect", stack.endpoint,
                                "--robot-id", stack.robot_id, "-o", str(bag), "--quiet"], cwd=REPO_ROOT, env=_env(),
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
        try:
            deadline = time.monotonic() + 120.0
            while not (bag / "metadata.yaml").exists() and not any(bag.glob("*.mcap")):
                if rec.poll() is not None or time.monotonic() > deadline:  # the robot moves once the bag is open
                    raise RuntimeError("zagv record did not start recording")
                time.sleep(0.05)
            runs, ready_sim_s, leg_starts_s = asyncio.run(_drive(sc, stack))
            if estop_at_s is not None:
                # the black box holds what it saw since it was ready (before `zagv: ready`): a full minute of it
                # lies before the e-stop only once the sim clock is a minute past that, whatever the machine's load
                estop_s = asyncio.run(_estop_at(stack, max(estop_at_s, ready_sim_s + BLACKBOX_MINUTE_S + 2.0)))
                # this e-stop's bag: a loaded machine may have saved an earlier one (a drive fault) before it
                stack.wait_line(r"black box saved: \S*_estop\b", timeout_s=120.0)
        finally:
            rec.send_signal(2)
            try:
                out, _ = rec.communicate(timeout=300)  # it writes what it still holds: minutes on a loaded machine
            except subprocess.TimeoutExpired:
                rec.kill()
                out, _ = rec.communicate()
                raise RuntimeError("zagv record did not stop within 300 s of SIGINT:\n"
                                   + out.decode(errors="replace")) from None
            for s in subs:
                s.undeclare()
        if rec.returncode != 0:
            raise RuntimeError(f"zagv record failed ({rec.returncode}):\n{out.decode(errors='replace')}")
        cpu_s = _children_cpu_s() - cpu0
    result = CorridorRecording(bag=bag, published=published, record_cpu_s=cpu_s,
                               world_yaml=run_dir / "stack" / "world.yaml", estop_s=estop_s,
                               blackbox_dir=run_dir / "stack" / "blackbox", leg_starts_s=leg_starts_s)
    goals_done = [g for r in runs for g in r["goals"]]
    result.goals, result.goals_reached = len(goals_done), sum(1 for g in goals_done if g["reached"])
    result.sim_s = bag_span_s(bag)
    return result


def bag_span_s(bag: Path) -> float:
    """Robot seconds between the first and the last message of a recording."""
    from services.recorder.source import BagSource

    with BagSource(bag) as src:
        return (src.end_ns - src.start_ns) / 1e9


async def _drive(sc, stack: Stack) -> tuple[list[dict], float, list[float]]:  # Scenario
    """The scenario's goals in order from the start pose, without re-placing the robot: localization keeps the
    initial pose of its configuration, so that a replay into a fresh localization starts from the same prior.
    Returns the runs, the sim time at which the ready stack was first seen publishing and the sim time at which
    each goal was sent."""
    from services.scenario.client import Client, wait_until
    from services.scenario.runner import query_until, run_goal

    c = Client(stack.session(), stack.keys, asyncio.get_running_loop())
    try:
        await wait_until(lambda: c.truth is not None and c.odom_count > 5, "no ground truth and odometry", 60.0)
        ready_sim_s = c.sim_time
        # the filter is initialised inside the bag, as an operator would at the start of a session: the recording
        # holds that request (localization's service events), and a replay issues it again before the same scan, so
        # the replayed filter starts where the live one did (AMCL's generator restarts from its seed at each
        # initialisation) instead of from whatever the live one had made of the scans before the bag opened
        assert c.truth is not None
        start = m.Pose2D(x=c.truth.pose.x, y=c.truth.pose.y, theta=c.truth.pose.theta)
        reply = await query_until(c, "localization/initial_pose",
                                  m.InitialPoseRequest(pose=start, covariance=INITIAL_COVARIANCE), 60.0)
        if not reply.ok:
            raise RuntimeError(f"localization/initial_pose refused: {reply.message}")
        # the bag opens with the robot at rest: a localization fed the bag settles there (at-rest updates) as the
        # recorded one did before the bag opened, instead of converging while the robot already drives
        rest_until_s = c.sim_time + REST_BEFORE_DRIVING_S
        await wait_until(lambda: c.sim_time >= rest_until_s, f"{REST_BEFORE_DRIVING_S} s of sim time at rest", 300.0)
        goals, leg_starts_s = [], []
        for k, g in enumerate(sc.goals, 1):
            leg_starts_s.append(c.sim_time)
            goals.append(await run_goal(c, sc, 1, k, g, 300.0, None))
        await c.sim_sleep(1.0)  # a sim second more: the last goal's messages reach the recorder as they reached us
    finally:
        c.close()
    return [{"run": 1, "goals": goals}], ready_sim_s, leg_starts_s


async def _estop_at(stack: Stack, at_s: float) -> float:
    """Wait for sim time ``at_s``, e-stop the drive; returns the sim time of the e-stop."""
    from services.common.node import query
    from services.scenario.client import Client, wait_until

    c = Client(stack.session(), stack.keys, asyncio.get_running_loop())
    try:
        await wait_until(lambda: c.sim_time >= at_s, f"sim time {at_s} s", 600.0)
        t = c.sim_time
        reply = await query(c.session, stack.keys, "drive/estop", m.Empty(), timeout_s=10.0)
        if not reply.ok:
            raise RuntimeError(f"drive/estop refused: {reply.message}")
        return t
    finally:
        c.close()


def replay_into_localization(bag: Path, world_yaml: Path, run_dir: Path, *, rate: float = 1.0,
                             seed: int = AMCL_SEED) -> list[m.Transform2D]:
    """Localization alone on ``world_yaml``, fed the bag's scan and odom by ``zagv replay``; the map -> odom
    transforms it publishes (one per scan once localized)."""
    run_dir.mkdir(parents=True, exist_ok=True)
    config = run_dir / "replay.toml"
    config.write_text(f"[clock]\nuse_sim_time = true\n\n[localization]\nrandom_seed = {seed}\n")
    poses: list[m.Transform2D] = []
    lock = threading.Lock()
    with Stack(run_dir, ["localization"], sim=False, map_yaml=str(world_yaml),
               extra_args=["--config", str(config)]).start(ready_timeout_s=300.0) as stack:
        session = stack.session()

        def on_tf(sample: zenoh.Sample) -> None:
            with lock:
                poses.append(codec.decode_as(m.Transform2D, sample.payload.to_bytes()))

        sub = session.declare_subscriber(stack.keys("tf/map_odom"), on_tf)
        subprocess.run([sys.executable, "-m", "services.cli", "replay", str(bag), "scan", "odom", "--connect",
                        stack.endpoint, "--robot-id", stack.robot_id, "--rate", str(rate), "--quiet"],
                       cwd=REPO_ROOT, env=_env(), check=True, stdin=subprocess.DEVNULL, timeout=3600)
        time.sleep(1.0)  # the last poses arrive (none is stamped late: at rest the filter does not update)
        sub.undeclare()
    return poses


def map_trajectory(map_odom: list[m.Transform2D], odom: list[m.Odometry]) -> tuple[np.ndarray, np.ndarray]:
    """The robot's map pose at each odom stamp after the first map -> odom: the latest map -> odom (by stamp)
    composed with that odom pose; (stamps (N,), poses (N, 3))."""
    tf = sorted(map_odom, key=lambda t: t.stamp)
    tf_stamps = np.array([t.stamp for t in tf])
    out_t, out_p = [], []
    for o in odom:
        i = int(np.searchsorted(tf_stamps, o.stamp, side="right")) - 1
        if i < 0:
            continue
        a = tf[i]
        out_t.append(o.stamp)
        out_p.append(compose((a.x, a.y, a.theta), (o.pose.x, o.pose.y, o.pose.theta)))
    return np.array(out_t), np.array(out_p).reshape(-1, 3)


def trajectory_rms_m(recorded: list[m.Transform2D], replayed: list[m.Transform2D],
                     odom: list[m.Odometry]) -> tuple[float, int]:
    """RMS position difference of the two map trajectories (``map_trajectory``) over the odom stamps both cover;
    (rms_m, number of poses compared)."""
    t_rec, p_rec = map_trajectory(recorded, odom)
    t_rep, p_rep = map_trajectory(replayed, odom)
    if not len(t_rec) or not len(t_rep):
        return float("inf"), 0
    common, i_rec, i_rep = np.intersect1d(t_rec, t_rep, return_indices=True)
    if not len(common):
        return float("inf"), 0
    d = p_rec[i_rec, :2] - p_rep[i_rep, :2]
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1)))), len(common)


def trajectory_rms_per_leg_m(recorded: list[m.Transform2D], replayed: list[m.Transform2D], odom: list[m.Odometry],
                             leg_starts_s: list[float]) -> list[tuple[float, int]]:
    """``trajectory_rms_m`` over each leg: before the first goal (at rest), then from each goal's start to the next;
    (rms_m, poses compared) per leg (NaN, 0 where none)."""
    bounds = [-np.inf, *leg_starts_s, np.inf]
    out = []
    for lo, hi in zip(bounds[:-1], bounds[1:], strict=True):
        leg = [o for o in odom if lo <= o.stamp < hi]
        out.append(trajectory_rms_m(recorded, replayed, leg) if leg else (float("nan"), 0))
    return out


def replay_speed_factor(bag: Path) -> float:
    """Bag seconds per wall second of ``zagv replay --rate 0`` (publishing into a router with no subscriber)."""
    from services.common.ports import free_port, wait_listening

    port = free_port()
    router = subprocess.Popen([sys.executable, "-m", "services.cli", "router", "--listen", f"tcp/127.0.0.1:{port}"],
                              cwd=REPO_ROOT, env=_env(), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        wait_listening(port, 30.0)
        bag_s = bag_span_s(bag)
        t0 = time.monotonic()
        # topics only: with no service listening, each recorded request would wait out --service-timeout
        subprocess.run([sys.executable, "-m", "services.cli", "replay", str(bag), "--rate", "0", "--quiet",
                        "--no-service-requests", "--connect", f"tcp/127.0.0.1:{port}"], cwd=REPO_ROOT, env=_env(),
                       check=True, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL)
        return bag_s / (time.monotonic() - t0)
    finally:
        router.terminate()
        router.wait()


def bag_mb(bag: Path) -> float:
    return sum(f.stat().st_size for f in bag.rglob("*") if f.is_file()) / 1e6


def bench_record() -> list[BenchRow]:
    with tempfile.TemporaryDirectory(prefix="zagv-bench-") as tmp:
        rec = record_corridor(Path(tmp))
        minutes = rec.sim_s / 60.0
        return [
            BenchRow("record.mb_per_min", bag_mb(rec.bag) / minutes, "MB/min", "corridor Table 3 run, all topics"),
            BenchRow("record.cpu_cores", rec.record_cpu_s / rec.sim_s, "cores", "zagv record at 1x; <= 0.1"),
            BenchRow("replay.speed_factor", replay_speed_factor(rec.bag), "x", "bag s per wall s, --rate 0; >= 5"),
        ]


BENCHES = [("record", bench_record)]
