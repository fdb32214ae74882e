"""Drive benchmarks: kinematics cost, and the control loop at a 1 kHz target against the simulated CAN bus.

``kinematics.ik_fk_us``: one inverse + least-squares forward kinematics of the two-module chassis (median, us);
``kinematics.command_us``: one full command path (limits, IK, optimisation, motor units) plus one odometry update.

The ``drive`` group starts its own processes on free loopback ports: a Zenoh router, the
simulated CAN bus (``services.sim.canbus``), the simulator (its emulated RoboteQ controllers, wall-paced at 1x)
and the drive service on the wall clock with ``drive.rate_hz = 1000`` and its configured RPDO refresh (on change,
else every ``drive.rpdo_refresh_s``). Rows:

- ``drive.loop_hz`` / ``drive.jitter_p99_ms``: the loop's own measurement (``wheels``: mean rate and p99 of
  |period - 1 ms| over its last 2000 periods) after ``settle_s`` of running without commands.
- ``drive.cmd_to_can_p99_ms``: a command put on the drive's command key (``drive.command_source``, by default
  ``safety/cmd_vel``: the collision monitor's output) by a Zenoh session with the services' settings (a peer, as the
  monitor publishes it: directly to drive once the router has introduced them) until
  the RPDO1 frame carrying the new traction speed goes onto the simulated bus (the bus's own frame timestamp, seen
  by a CAN client on it). The command alternates between +vy and -vy (the wheels stay at +-90 deg, the traction
  speed changes sign, whichever of the two equivalent module states the optimiser holds) and the acceleration limits
  are raised for this run, so the very first RPDO after the command differs. It includes the Zenoh hop and the
  drive's websocket to the simulated bus (a Python server), so it is an upper bound of the drive's share;
  ``drive.rx_to_rpdo_*`` is that share alone, measured by the drive (cmd_vel callback -> RPDO written).
"""

from __future__ import annotations

import bisect
import contextlib
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from proto import codec
from proto.keys import Keys
from proto.messages import Twist2D, WheelStates
from services.common.bench import BenchRow, time_calls
from services.common.motor_units import MotorUnits
from services.common.ports import free_port
from services.common.robot import RobotSpec
from services.common.session import open_session
from services.common.settings import ZenohSettings
from services.drive.controller import DriveController, ModuleFeedback, WheelOdometry
from services.drive.cpu_latency import NO_CPU_LATENCY_REQUEST, cpu_latency_in_force_us
from services.drive.kinematics import SwerveKinematics, Twist

REPO_ROOT = Path(__file__).resolve().parents[2]


def bench_kinematics() -> list[BenchRow]:
    robot = RobotSpec()
    kin = SwerveKinematics([(m.x_m, m.y_m) for m in robot.modules])
    twist = Twist(0.12, -0.07, 0.3)

    def ik_fk() -> None:
        kin.to_twist(kin.to_module_states(twist))

    units = [MotorUnits(), MotorUnits()]
    ctl = DriveController(kin, units, robot.twist_limits())
    odo = WheelOdometry(kin, units)
    counts = [0]

    def step() -> None:
        counts[0] += 37
        ctl.command(twist, 0.001, (0.1, -0.2))
        odo.update([ModuleFeedback(counts[0], 1000, 300), ModuleFeedback(counts[0], -2000, 310)])

    t_ikfk = time_calls(ik_fk, repeat=5000)
    t_step = time_calls(step, repeat=5000)
    return [BenchRow("kinematics.ik_fk_us", float(np.median(t_ikfk)) * 1e6, "us", "< 50 (1 kHz loop budget)"),
            BenchRow("kinematics.command_us", float(np.median(t_step)) * 1e6, "us", "< 200")]


def realtime_allowed() -> bool:
    """Whether this machine lets us run processes SCHED_FIFO (root or CAP_SYS_NICE, and ``chrt`` present)."""
    if shutil.which("chrt") is None:
        return False
    return subprocess.run(["chrt", "-f", "1", "true"], capture_output=True).returncode == 0


def _spawn(*args: str, fifo: int = 0) -> subprocess.Popen[bytes]:
    env = {**os.environ, "PYTHONPATH": str(REPO_ROOT), "ZAGV_LOG_LEVEL": "WARNING"}
    prefix = ["chrt", "-f", str(fifo)] if fifo > 0 else []
    return subprocess.Popen([*prefix, sys.executable, "-m", *args], cwd=REPO_ROOT, env=env,
                            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)


class _RpdoWatch:
    """A CAN client on the simulated bus, in its own process, recording (bus time, traction rpm) of node 1's RPDO1.

    The bus time is the frame's timestamp set by the simulated bus when the frame went onto it (python-can's virtual
    bus stamps ``time.time()`` on send and the remote protocol carries it), so the relay to this client is not part
    of the measurement. A separate process keeps its work off the interpreter that publishes the commands.
    """

    def __init__(self, channel: str, out: Path, cob_id: int = 0x201) -> None:
        self.out = out
        self.proc = _spawn("services.drive.bench", "watch", channel, str(out), str(cob_id))
        self.frames: list[tuple[float, int]] = []

    def wait_ready(self, timeout_s: float = 30.0) -> None:
        deadline = time.monotonic() + timeout_s
        while not (self.out.exists() and self.out.stat().st_size > 0):
            if time.monotonic() > deadline:
                raise RuntimeError("drive bench: the CAN observer saw no RPDO frame")
            time.sleep(0.05)

    def collect(self) -> None:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.proc.pid, 15)
        self.proc.wait(5)
        rows = []
        for line in self.out.read_text().splitlines():
            parts = line.split()
            if len(parts) == 2:
                rows.append((float(parts[0]), int(parts[1])))
        self.frames = sorted(rows)

    def first_flip_after(self, t0: float, min_rpm: float) -> float | None:
        """Bus time of the first frame after ``t0`` whose speed has the opposite sign of the last one before it."""
        i = bisect.bisect_left(self.frames, (t0, -(2**31)))
        if i == 0:
            return None
        before = self.frames[i - 1][1]
        for t, rpm in self.frames[i:i + 200]:
            if rpm * before < 0 and abs(rpm) >= min_rpm:
                return t
        return None

    def close(self) -> None:
        if self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.proc.pid, 9)
            self.proc.wait()
        shutil.rmtree(self.out.parent, ignore_errors=True)


def watch_main(channel: str, out: str, cob_id: int) -> None:
    """``python -m services.drive.bench watch CHANNEL FILE COB_ID``: log (bus time, rpm) lines until SIGTERM."""
    import signal

    import can

    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    bus = can.Bus(interface="remote", channel=channel)
    with open(out, "w") as f:
        while not stop.is_set():
            msg = bus.recv(0.1)
            if msg is not None and msg.arbitration_id == cob_id and len(msg.data) == 8:
                f.write(f"{msg.timestamp:.6f} {int.from_bytes(msg.data[:4], 'little', signed=True)}\n")
                f.flush()
    with contextlib.suppress(Exception):
        bus.shutdown()


def _stats(session, keys: Keys) -> dict:  # zenoh.Session
    for reply in session.get(keys("@stats/drive"), timeout=2.0):
        if reply.ok is not None:
            return json.loads(reply.ok.payload.to_bytes())
    return {}


def _latency_in_force() -> str:
    try:
        latency_us = cpu_latency_in_force_us()
    except OSError:
        return "unknown"
    return "none" if latency_us >= NO_CPU_LATENCY_REQUEST else f"{latency_us} us"


def bench_drive(settle_s: float = 4.0, samples: int = 300, realtime: bool | None = None,
                rpdo_refresh_s: float | None = None, rate_hz: float = 1000.0,
                cpu_latency_us: int | None = 0) -> list[BenchRow]:
    """The drive at 1 kHz against the simulated bus. ``realtime`` (default: when the machine allows it) runs the
    drive as deployed (process SCHED_FIFO 10, control thread 50, no spinning, and its CPU latency request
    ``drive.cpu_latency_us = cpu_latency_us``: idle CPUs poll, as the robot's drive unit keeps every CPU polling), and
    the Zenoh router and the CAN bus server at SCHED_FIFO 10 (the bus stands in for CAN hardware); otherwise
    everything is time-shared and no latency request is made. The ``drive.loop_hz`` row's note gives the request
    the kernel had in force while the commands were measured.
    ``rpdo_refresh_s`` None keeps the drive's configured RPDO refresh (on change, else every
    ``drive.rpdo_refresh_s``); 0 sends RPDO1 every cycle, 2000 frames a second for the simulated bus to relay at 1 kHz.
    """
    if realtime is None:
        realtime = realtime_allowed()
    fifo = 10 if realtime else 0
    zenoh_port, can_port, lidar_port = free_port(), free_port(), free_port()
    endpoint = f"tcp/127.0.0.1:{zenoh_port}"
    channel = f"ws://127.0.0.1:{can_port}/"
    keys = Keys("r1")
    # the router in its own process: a router embedded here would share this process's interpreter with the busy
    # CAN observer thread, and forwarding would wait for it
    procs = [_spawn("services.cli", "router", "--listen", endpoint, fifo=fifo),
             _spawn("services.sim.canbus", "--port", str(can_port), fifo=fifo)]
    watcher = None
    watch = None
    client = None
    try:
        time.sleep(0.5)
        watcher = open_session(ZenohSettings(mode="client", connect=[endpoint]))
        procs.append(_spawn("services.sim", "--connect", endpoint, "--set", f'sim.can_channel="{channel}"',
                            "--set", f"sim.lidar_port={lidar_port}", "--set", 'sim.world="empty_room"',
                            "--set", "sim.speed_factor=1.0"))
        procs.append(_spawn("services.drive", "--connect", endpoint, "--set", f'drive.can_channel="{channel}"',
                            "--set", f"drive.rate_hz={rate_hz}", "--set", "robot.ax_max_mps2=1000.0",
                            "--set", "robot.ay_max_mps2=1000.0", "--set", "robot.alpha_max_radps2=1000.0",
                            "--set", f"drive.realtime_priority={50 if realtime else 0}",
                            *([] if rpdo_refresh_s is None else ["--set", f"drive.rpdo_refresh_s={rpdo_refresh_s}"]),
                            "--set", f"drive.spin_s={0.0 if realtime else 0.0003}",
                            *(["--set", f"drive.cpu_latency_us={cpu_latency_us}"]
                              if realtime and cpu_latency_us is not None else []), fifo=fifo))
        latest: list[WheelStates] = []
        key = keys("wheels")
        sub = watcher.declare_subscriber(key, lambda s: latest.append(codec.decode_as(WheelStates,
                                                                                     s.payload.to_bytes(), key)))
        deadline = time.monotonic() + 60
        while not (latest and latest[-1].link_ok):
            if time.monotonic() > deadline:
                raise RuntimeError("drive bench: the drive never reported a live CAN link")
            time.sleep(0.05)
        time.sleep(settle_s)
        quiet = latest[-1]
        mode = "SCHED_FIFO" if realtime else "time-shared"
        rows = [BenchRow("drive.loop_hz", quiet.loop_hz, "Hz",
                         f"1000 (target; {mode}; CPU latency request in force: {_latency_in_force()})"),
                BenchRow("drive.jitter_p99_ms", quiet.loop_jitter_p99_ms, "ms", "<= 0.2")]

        watch = _RpdoWatch(channel, Path(tempfile.mkdtemp(prefix="zagv-bench-")) / "rpdo.txt")
        watch.wait_ready()
        client = open_session(ZenohSettings(connect=[endpoint]))  # a service's session, as nav publishes cmd_vel
        # the direct links to the drive and the simulator (the only peers) come up through the router's gossip; until
        # then a command takes the router's hop
        deadline = time.monotonic() + 10.0
        while len(list(client.info.peers_zid())) < 2 and time.monotonic() < deadline:
            time.sleep(0.05)
        from services.drive.config import DriveConfig
        pub = client.declare_publisher(keys(DriveConfig().command_source), express=True)
        vy = 0.08
        rpm = vy * 30.0 * 60.0 / (2.0 * math.pi * 0.1)  # motor units of the default robot (eq. 7)
        for _ in range(50):  # steer the wheels to 90 deg first
            pub.put(codec.encode(Twist2D(vy=vy)))
            time.sleep(0.02)
        sent = []
        sign = 1.0
        for _ in range(samples):
            sign = -sign
            payload = codec.encode(Twist2D(vy=sign * vy))
            t0 = time.time()  # the simulated bus stamps frames with time.time()
            pub.put(payload)
            sent.append((t0, sign))
            time.sleep(0.02)
        pub.put(codec.encode(Twist2D()))
        time.sleep(0.2)
        watch.collect()
        latencies = []
        late = 0
        for t0, _ in sent:  # a command not on the bus before the next one counts as 20 ms (censored)
            t = watch.first_flip_after(t0, 0.5 * rpm)
            if t is None or t - t0 >= 0.02:
                late += 1
                t = t0 + 0.02
            latencies.append(t - t0)
        sub.undeclare()
        lat = np.asarray(latencies) * 1e3
        rows += [BenchRow("drive.cmd_to_can_p99_ms", float(np.percentile(lat, 99)) if len(lat) else math.nan, "ms",
                          "<= 1.0"),
                 BenchRow("drive.cmd_to_can_p50_ms", float(np.percentile(lat, 50)) if len(lat) else math.nan, "ms",
                          f"{late}/{samples} commands not on the bus within 20 ms")]
        with_cmds = latest[-1]
        rows.append(BenchRow("drive.jitter_p99_under_cmds_ms", with_cmds.loop_jitter_p99_ms, "ms",
                             "with a cmd_vel every 20 ms"))
        stats = _stats(watcher, keys)
        rows += [BenchRow("drive.rx_to_rpdo_p50_ms", stats.get("cmd_to_bus_p50_ms", math.nan), "ms",
                          "inside drive: cmd_vel callback -> RPDO written"),
                 BenchRow("drive.rx_to_rpdo_p99_ms", stats.get("cmd_to_bus_p99_ms", math.nan), "ms", "")]
        return rows
    finally:
        if watch is not None:
            watch.close()
        if client is not None:
            client.close()
        for p in reversed(procs):
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.pid, 15)
        for p in reversed(procs):
            try:
                p.wait(5)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, 9)
                p.wait()
        if watcher is not None:
            watcher.close()


BENCHES = [("kinematics", bench_kinematics), ("drive", bench_drive)]


if __name__ == "__main__":
    if len(sys.argv) == 5 and sys.argv[1] == "watch":
        watch_main(sys.argv[2], sys.argv[3], int(sys.argv[4]))
    else:
        sys.exit("usage: python -m services.drive.bench watch CHANNEL FILE COB_ID (a helper of the drive bench)")
