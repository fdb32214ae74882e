"""A site on loopback: a site router, one router per robot linked to it, one simulated robot stack per robot
(``zagv up --sim --external-router``, each its own sim, CAN bus and LMS111) and the fleet service on the site router.

Links are plain TCP on loopback (the TLS and access control of deploy/zenoh/ are tested on their own in
tests/test_deploy_site_acl.py); every router config has multicast scouting off. Each robot starts at its own pose
of the same world, so all of them fit on the shared map.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import zenoh

from proto import codec
from proto.messages import GroundTruth
from services.common.ports import free_port
from services.common.session import open_session
from services.common.settings import ZenohSettings
from services.launch.stack_process import REPO_ROOT, Stack
from tests.support.waiting import wait_for_sync

#: what a robot needs to take a goal: no HMI, no recorder, no collision monitor (drive then obeys cmd_vel)
ROBOT_SERVICES = ["sim", "drive", "lidar", "localization", "nav"]


@dataclass
class RobotPlan:
    robot_id: str
    start: tuple[float, float, float]


class Process:
    """A child process whose output lines are kept (and written to ``log``), in its own process group."""

    def __init__(self, argv: list[str], log: Path) -> None:
        env = {**os.environ, "PYTHONPATH": str(REPO_ROOT), "PYTHONUNBUFFERED": "1",
               "ZAGV_PARENT_PID": str(os.getpid())}
        self.log = log
        self.proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                     cwd=REPO_ROOT, env=env, start_new_session=True)
        self.lines: list[str] = []
        self._lock = threading.Lock()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stdout
        with open(self.log, "ab") as f:
            for raw in self.proc.stdout:
                f.write(raw)
                f.flush()
                with self._lock:
                    self.lines.append(raw.decode(errors="replace").rstrip("\n"))

    def output(self, last: int = 60) -> str:
        with self._lock:
            return "\n".join(self.lines[-last:])

    def wait_line(self, pattern: str, timeout_s: float) -> re.Match[str]:
        rx = re.compile(pattern)

        def found() -> re.Match[str] | None:
            with self._lock:
                for line in self.lines:
                    if m := rx.search(line):
                        return m
            assert self.proc.poll() is None, f"{self.log.name} exited:\n{self.output()}"
            return None

        return wait_for_sync(found, timeout_s=timeout_s, poll_s=0.02,
                             message=f"no /{pattern}/ from {self.log.name}:\n{self.output()}")

    def kill(self) -> None:
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGKILL)
        self.proc.wait()

    def stop(self) -> None:
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.kill()


def router_config(listen: str, connect: list[str], gossip: bool) -> dict:
    """A router on loopback: ``listen``, dialling ``connect``; gossip (for a robot's peers) or none (the site)."""
    return {"mode": "router", "listen": {"endpoints": [listen]}, "connect": {"endpoints": connect},
            "scouting": {"multicast": {"enabled": False},
                         "gossip": {"enabled": True, "multihop": False,
                                    "autoconnect": {"router": [], "peer": ["router", "peer"]}} if gossip
                         else {"enabled": False}}}


class Site:
    """Start with ``start()``; always ``stop()`` (the fixture does)."""

    def __init__(self, root: Path, robots: list[RobotPlan], *, world: str = "corridor", speed: float = 1.0,
                 services: list[str] | None = None) -> None:
        self.root = root
        self.robots = robots
        self.site_port = free_port()
        self.site_endpoint = f"tcp/127.0.0.1:{self.site_port}"
        self.fleet_port = free_port()
        self.router_ports = {r.robot_id: free_port() for r in robots}
        self.world = world
        self.speed = speed
        self.services = services or ROBOT_SERVICES
        self.site_router: Process | None = None
        self.routers: dict[str, Process] = {}
        self.stacks: dict[str, Stack] = {}
        self.fleet: Process | None = None
        self._sessions: list[zenoh.Session] = []
        self.truth: dict[str, GroundTruth] = {}
        self._truth_lock = threading.Lock()

    # ------------------------------------------------------------------ lifetime

    def start_site_router(self) -> float:
        """Start the site router; returns the wall (monotonic) time it said it listens."""
        path = self.root / "site-router.json5"
        path.write_text(json.dumps(router_config(self.site_endpoint, [], gossip=False)))
        n = sum(1 for p in self.root.glob("site-router*.log"))
        self.site_router = Process([sys.executable, "-m", "services.cli", "router", "--config", str(path)],
                                   self.root / f"site-router{n}.log")
        self.site_router.wait_line(r"listening on", timeout_s=60)
        return time.monotonic()

    def start(self, ready_timeout_s: float = 240.0) -> Site:
        self.root.mkdir(parents=True, exist_ok=True)
        self.start_site_router()
        for r in self.robots:
            endpoint = f"tcp/127.0.0.1:{self.router_ports[r.robot_id]}"
            path = self.root / f"router-{r.robot_id}.json5"
            path.write_text(json.dumps(router_config(endpoint, [self.site_endpoint], gossip=True)))
            self.routers[r.robot_id] = Process(
                [sys.executable, "-m", "services.cli", "router", "--config", str(path)],
                self.root / f"router-{r.robot_id}.log")
        for r in self.robots:
            self.routers[r.robot_id].wait_line(r"listening on", timeout_s=60)
            endpoint = f"tcp/127.0.0.1:{self.router_ports[r.robot_id]}"
            x, y, th = r.start
            sets = [f"sim.start_pose=[{x}, {y}, {th}]", f"localization.initial_pose_x={x}",
                    f"localization.initial_pose_y={y}", f"localization.initial_pose_yaw={th}"]
            run_dir = self.root / r.robot_id
            run_dir.mkdir()
            stack = Stack(run_dir, self.services, world=self.world, speed=self.speed, robot_id=r.robot_id,
                          extra_args=["--external-router", endpoint, *(a for s in sets for a in ("--set", s))])
            stack.endpoint = endpoint
            self.stacks[r.robot_id] = stack
            stack.start(wait_ready=False)
        fleet_state = self.root / "fleet"
        self.fleet = Process([sys.executable, "-m", "services.fleet", "--robot-id", "site",
                              "--connect", self.site_endpoint, "--set", f"fleet.port={self.fleet_port}",
                              "--set", f'fleet.state_dir="{fleet_state}"'], self.root / "fleet.log")
        for stack in self.stacks.values():
            stack.wait_line(r"^zagv: ready", timeout_s=ready_timeout_s)
        for rid in self.stacks:
            session = self.robot_session(rid)
            session.declare_subscriber(f"agv/{rid}/sim/ground_truth", self._truth_handler(rid))
        return self

    def stop(self) -> None:
        for s in self._sessions:
            with contextlib.suppress(Exception):  # already closed
                s.close()
        self._sessions.clear()
        # every stack and process at once: each may take seconds to stop on a loaded machine
        stoppers = [*(s.stop for s in self.stacks.values()), *(p.stop for p in [self.fleet] if p)]
        threads = [threading.Thread(target=stop) for stop in stoppers]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        for router in [*self.routers.values(), *([self.site_router] if self.site_router else [])]:
            router.stop()

    # ------------------------------------------------------------------ access

    @property
    def fleet_url(self) -> str:
        return f"http://127.0.0.1:{self.fleet_port}"

    def fleet_password(self, timeout_s: float = 60.0) -> str:
        assert self.fleet
        return self.fleet.wait_line(r"first-run password: (\S+)", timeout_s=timeout_s).group(1)

    def robot_session(self, robot_id: str) -> zenoh.Session:
        """A client session on the robot's own router (works whatever happens to the site router)."""
        s = open_session(ZenohSettings(mode="client", connect=[f"tcp/127.0.0.1:{self.router_ports[robot_id]}"]))
        self._sessions.append(s)
        return s

    def _truth_handler(self, robot_id: str):
        def on_sample(sample: zenoh.Sample) -> None:
            msg = codec.decode_as(GroundTruth, sample.payload.to_bytes(), str(sample.key_expr))
            with self._truth_lock:
                self.truth[robot_id] = msg
        return on_sample

    def true_pose(self, robot_id: str) -> tuple[float, float, float] | None:
        with self._truth_lock:
            t = self.truth.get(robot_id)
        return (t.pose.x, t.pose.y, t.pose.theta) if t is not None else None

    def collided(self) -> list[str]:
        with self._truth_lock:
            return sorted(rid for rid, t in self.truth.items() if t.collided)
