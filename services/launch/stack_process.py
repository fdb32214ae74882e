"""A robot stack in a subprocess: ``zagv up`` on free loopback ports, for tests, benchmarks and scenarios.

``zagv up`` embeds the router and supervises each service as its own process, exactly as users run it. ``Stack``
reads its output (kept in ``<run_dir>/stack.log``), waits for ``zagv: ready``, hands out Zenoh client sessions,
knows each service's pid, and always tears everything down (SIGTERM, then SIGKILL of the whole process group).
"""

from __future__ import annotations

import contextlib
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

from proto.keys import Keys
from services.common.ports import ephemeral_range, free_port
from services.common.session import open_session
from services.common.settings import ZenohSettings

REPO_ROOT = Path(__file__).resolve().parents[2]


def free_port_block(n: int) -> int:
    """The first of ``n`` consecutive free loopback ports (a fleet's robot k uses base + k)."""
    if n <= 1:
        return free_port()
    for _ in range(200):
        base = free_port()
        if base + n > 65535 or base < ephemeral_range()[0] < base + n:
            continue
        try:
            with contextlib.ExitStack() as held:
                for p in range(base, base + n):
                    sock = held.enter_context(socket.socket())
                    sock.bind(("127.0.0.1", p))
            return base
        except OSError:
            continue
    raise RuntimeError(f"no block of {n} free ports on 127.0.0.1")


class Stack:
    """One ``zagv up`` process and what the test needs to talk to it."""

    def __init__(self, run_dir: Path, services: list[str] | None = None, *, sim: bool = True,
                 world: str = "corridor", map_yaml: str | None = None, speed: float = 1.0,
                 extra_args: list[str] | None = None, robot_id: str = "r1", fleet_size: int = 1) -> None:
        """``fleet_size`` > 1: room for that many robots (``--robots``/``--robot`` in ``extra_args``): each robot
        k gets the base CAN, LMS111 and HMI ports + k."""
        self.run_dir = run_dir
        self.services = services
        self.robot_id = robot_id
        self.keys = Keys(robot_id)
        self.zenoh_port = free_port()
        self.can_port, self.lidar_port, self.http_port = (free_port_block(fleet_size) for _ in range(3))
        self.endpoint = f"tcp/127.0.0.1:{self.zenoh_port}"
        self.argv = [sys.executable, "-m", "services.cli", "up", "--robot-id", robot_id,
                     "--zenoh-port", str(self.zenoh_port), "--can-port", str(self.can_port),
                     "--lidar-port", str(self.lidar_port), "--http-port", str(self.http_port),
                     "--run-dir", str(run_dir), "--speed", str(speed)]
        if sim:
            self.argv.append("--sim")
        if map_yaml:
            self.argv += ["--map", map_yaml]
        else:
            self.argv += ["--world", world]
        if services is not None:
            self.argv += ["--only", ",".join(services)]
            if "hmi_api" not in services:
                self.argv.append("--headless")
        self.argv += extra_args or []
        self.lines: list[str] = []
        self._lock = threading.Lock()
        self.proc: subprocess.Popen[bytes] | None = None
        self._sessions: list = []

    # ------------------------------------------------------------------ lifetime

    def start(self, ready_timeout_s: float = 90.0, *, wait_ready: bool = True) -> Stack:
        """Start ``zagv up`` and wait for ``zagv: ready`` (``wait_ready``), or only for its router: a test that
        provides a service's required inputs itself starts them then waits for ready."""
        # ZAGV_PARENT_PID: `zagv up` stops (and with it every service) when this process dies, however it dies
        env = {**os.environ, "PYTHONPATH": str(REPO_ROOT), "PYTHONUNBUFFERED": "1", "ZAGV_PARENT_PID": str(os.getpid())}
        self.proc = subprocess.Popen(self.argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                     stdin=subprocess.DEVNULL, cwd=REPO_ROOT, env=env, start_new_session=True)
        threading.Thread(target=self._read, daemon=True).start()
        self.wait_line(r"^zagv: ready" if wait_ready else r"^zagv: (router on|external router at)",
                       timeout_s=ready_timeout_s)
        return self

    def _read(self) -> None:
        assert self.proc and self.proc.stdout
        with open(self.run_dir / "stack.log", "ab") as log:
            for raw in self.proc.stdout:
                log.write(raw)
                log.flush()
                with self._lock:
                    self.lines.append(raw.decode(errors="replace").rstrip("\n"))

    def __enter__(self) -> Stack:
        """Starts the stack unless ``start`` already did (``with stack.start(...):`` must not start a second one)."""
        return self if self.proc is not None else self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def stop(self) -> None:
        for s in self._sessions:
            with contextlib.suppress(Exception):
                s.close()
        self._sessions.clear()
        if self.proc and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.proc.wait(timeout=15)
        if self.proc:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait()

    # ------------------------------------------------------------------ output

    def output(self) -> str:
        with self._lock:
            return "\n".join(self.lines)

    def wait_line(self, pattern: str, *, timeout_s: float, after: int = 0) -> re.Match[str]:
        """Wait for an output line matching ``pattern`` (searched from line ``after``)."""
        rx = re.compile(pattern)
        deadline = time.monotonic() + timeout_s
        while True:
            with self._lock:
                for line in self.lines[after:]:
                    m = rx.search(line)
                    if m:
                        return m
            if self.proc and self.proc.poll() is not None:
                raise AssertionError(f"zagv up exited ({self.proc.returncode}) before /{pattern}/:\n"
                                     + self.output()[-4000:])
            if time.monotonic() > deadline:
                raise AssertionError(f"no line /{pattern}/ within {timeout_s} s:\n" + self.output()[-4000:])
            time.sleep(0.02)

    def line_count(self) -> int:
        with self._lock:
            return len(self.lines)

    def process_of(self, service: str) -> str:
        """The supervisor's name of the process ``service`` runs in: its own, or its container's (the container's
        ``running a, b, ... in one process`` line) when it was never started on its own. In a fleet, ``r2.lidar``
        runs in ``r2.components``: the container line names its services without the robot."""
        robot, _, bare = service.rpartition(".")
        with self._lock:
            own = any(re.search(rf"^zagv\s+\| started {re.escape(service)} \(pid \d+\)", line) for line in self.lines)
            containers = [m.group(1) for line in self.lines
                          if (m := re.search(r"^(\S+)\s+\| .*\[zagv\.container\]: running (.+) in one process", line))
                          and bare in m.group(2).split(", ") and m.group(1).startswith(f"{robot}." if robot else "")]
        return containers[-1] if containers and not own else service

    def pid(self, service: str) -> int:
        """The pid of the newest instance of the process ``service`` runs in (from the supervisor's start lines)."""
        name = self.process_of(service)
        with self._lock:
            pids = [int(m.group(1)) for line in self.lines
                    if (m := re.search(rf"^zagv\s+\| started {re.escape(name)} \(pid (\d+)\)", line))]
        if not pids:
            raise AssertionError(f"{service} was never started:\n" + self.output()[-3000:])
        return pids[-1]

    # ------------------------------------------------------------------ zenoh

    def session(self):  # zenoh.Session
        """A Zenoh client session to the stack's router (closed at teardown)."""
        s = open_session(ZenohSettings(mode="client", connect=[self.endpoint]))
        self._sessions.append(s)
        return s


