"""Faults against the simulated robot (sim, drive, lidar, localization, nav, hmi_api under ``zagv up``).

The lidar reaches the emulated LMS111 through a proxy the test can cut. One stack serves the module: garbage on
every key a service subscribes to or serves, the LMS111 link cut, and SIGKILL of each service while the test
streams cmd_vel (each one restarted, healthy again, and its data flowing again).
"""

from __future__ import annotations

import json
import math
import os
import signal
import threading
import time
from collections.abc import Iterator

import pytest

from proto import codec
from proto.messages import GroundTruth, Twist2D, WheelStates
from proto.registry import QUERIES, TOPICS
from services.launch.stack_process import Stack
from tests.faults.tcp_cut import CuttableProxy
from tests.support.waiting import wait_for_sync

pytestmark = pytest.mark.integration

SERVICES = ["sim", "drive", "lidar", "localization", "nav", "hmi_api"]
#: the keys each service subscribes to (topics) or serves (queries), as the garbage must be counted
SUBSCRIBED = {
    "sim": {"sim/teleport": True, "sim/obstacles": True},  # the clock's source does not subscribe to it
    "drive": {"clock": False, "cmd_vel": False, "drive/enable": True, "drive/estop": True},
    "lidar": {"clock": False},
    "localization": {"clock": False, "odom": False, "scan": False, "localization/initial_pose": True},
    "nav": {"clock": False, "odom": False, "tf/map_odom": False, "pose": False, "scan": False, "map": False,
            "nav/goal": True, "nav/cancel": True},
    "hmi_api": {"clock": False, "map": False, "odom": False, "pose": False, "wheels": False, "scan": False,
                "cmd_vel": False, "nav/status": False, "nav/path": False, "particles": False, "tf/map_odom": False},
}
GARBAGE = [b"\x00garbage", b"\xff" * 64, b"", b"\x93\x01\x02"]


class Observer:
    """The latest stamps of the data each service produces, and a cmd_vel stream."""

    def __init__(self, stack: Stack) -> None:
        self.stack = stack
        self.session = stack.session()
        self.last_wall: dict[str, float] = {}
        self.wheels: WheelStates | None = None
        self.truth: GroundTruth | None = None
        self.lock = threading.Lock()
        for name in ("scan", "wheels", "odom", "sim/ground_truth", "tf/map_odom", "pose", "clock"):
            self.session.declare_subscriber(stack.keys(name), self._on(name))
        self.cmd = self.session.declare_publisher(stack.keys("cmd_vel"))
        self._streaming = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._stream, daemon=True)
        self._thread.start()

    def _on(self, name: str):
        key = self.stack.keys(name)

        def cb(sample) -> None:
            try:
                msg = codec.decode_as(TOPICS[name], sample.payload.to_bytes(), key)
            except codec.ProtoDecodeError:
                return  # the test's own garbage
            with self.lock:
                self.last_wall[name] = time.monotonic()
                if name == "wheels":
                    self.wheels = msg
                elif name == "sim/ground_truth":
                    self.truth = msg
        return cb

    def _stream(self) -> None:
        while not self._stop.wait(0.02):
            if self._streaming.is_set():
                self.cmd.put(codec.encode(Twist2D(vx=0.05, wz=0.1)))

    def streaming(self, on: bool) -> None:
        (self._streaming.set if on else self._streaming.clear)()

    def fresh(self, name: str, since: float) -> bool:
        with self.lock:
            return self.last_wall.get(name, -math.inf) > since

    def wait_fresh(self, name: str, since: float, timeout_s: float) -> float:
        """Wall s from ``since`` to the first ``name`` message after it."""
        wait_for_sync(lambda: self.fresh(name, since), timeout_s=timeout_s, message=f"no {name} after the fault")
        return self.last_wall[name] - since

    def stats(self, service: str) -> dict:
        for reply in self.session.get(self.stack.keys(f"@stats/{service}"), timeout=3.0):
            if reply.ok is not None:
                return json.loads(reply.ok.payload.to_bytes())
        return {}

    def close(self) -> None:
        self._stop.set()
        self._thread.join()


@pytest.fixture(scope="module")
def robot(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Stack, Observer, CuttableProxy]]:
    # each service in a process of its own, so that each can be killed alone (tests/faults/test_faults_nav.py kills
    # the composed process of zagv up's default)
    stack = Stack(tmp_path_factory.mktemp("service_faults"), SERVICES, world="corridor", speed=1.0,
                  extra_args=["--no-compose"])
    proxy = CuttableProxy(stack.lidar_port)
    stack.argv += ["--set", f"lidar.port={proxy.port}"]  # after the launcher's own lidar.port: this one wins
    observer = None
    try:
        stack.start()
        observer = Observer(stack)
        wait_for_sync(lambda: observer.fresh("scan", 0) and observer.fresh("wheels", 0), timeout_s=60,
                      message="no scan or wheels from the fresh stack")
        yield stack, observer, proxy
    finally:
        if observer:
            observer.close()
        stack.stop()
        proxy.close()


def test_garbage_on_every_subscribed_key_is_counted_and_survived(robot) -> None:
    stack, obs, _ = robot
    pids = {s: stack.pid(s) for s in SERVICES}
    assert {k for table in SUBSCRIBED.values() for k in table} <= set(TOPICS) | set(QUERIES)

    def send_garbage(names: set[str]) -> None:
        for name in sorted(names):
            for payload in GARBAGE:
                if name in QUERIES and name not in TOPICS:
                    if payload:  # an empty query payload is a valid default request
                        list(obs.session.get(stack.keys(name), payload=payload, timeout=3.0))
                else:
                    obs.session.put(stack.keys(name), payload)

    def uncounted() -> dict[str, set[str]]:
        missing = {}
        for service, table in SUBSCRIBED.items():
            bad = obs.stats(service).get("bad_payloads", {})
            if keys := {k for k in table if bad.get(stack.keys(k), 0) < 1}:
                missing[service] = keys
        return missing

    # a service's health token comes up before all its subscriptions: keys not counted yet get garbage again
    missing = uncounted()
    deadline = time.monotonic() + 20
    while missing and time.monotonic() < deadline:
        send_garbage(set().union(*missing.values()))
        time.sleep(0.5)  # let the garbage arrive before asking for the counts again
        missing = uncounted()
    assert not missing, f"garbage not counted (service: keys): {missing}"
    assert {s: stack.pid(s) for s in SERVICES} == pids, "a service died of garbage"
    since = time.monotonic()
    for name in ("scan", "wheels", "sim/ground_truth"):
        obs.wait_fresh(name, since, timeout_s=10)


def test_lms111_link_cut_lidar_reconnects(robot, fault_figures) -> None:
    stack, obs, proxy = robot
    obs.wait_fresh("scan", time.monotonic(), timeout_s=10)
    accepted = proxy.accepted
    cut_at = time.monotonic()
    proxy.cut()
    wait_for_sync(lambda: proxy.accepted > accepted, timeout_s=15, message="lidar never reconnected")
    reconnected = time.monotonic()
    fault_figures("lms111_link_reconnect_wall", reconnected - cut_at)
    recovered = obs.wait_fresh("scan", reconnected, timeout_s=40) + (reconnected - cut_at)
    fault_figures("lms111_link_recover_wall", recovered)
    assert obs.stats("lidar")["lidar"]["connects"] >= 2


@pytest.mark.parametrize("service", ["lidar", "localization", "hmi_api", "sim", "drive"])
def test_sigkill_during_motion_restarted_and_flowing_again(robot, service, fault_figures) -> None:
    stack, obs, _ = robot
    produces = {"lidar": "scan", "localization": "tf/map_odom", "hmi_api": None, "sim": "sim/ground_truth",
                "drive": "wheels"}[service]
    obs.streaming(True)
    try:
        old = stack.pid(service)
        mark = stack.line_count()
        killed = time.monotonic()
        os.kill(old, signal.SIGKILL)
        stack.wait_line(rf"^zagv\s+\| {service} killed by SIGKILL; restarting", timeout_s=5, after=mark)
        dead = time.monotonic()  # messages after this come from the new process
        # (a dead simulator also stops the sim clock, and with it the drive's loop: no wheel state is published
        # until the controllers are back, checked below)
        stack.wait_line(rf"^zagv: {service} healthy again", timeout_s=60, after=mark)
        fault_figures(f"{service}_sigkill_to_healthy_wall", time.monotonic() - killed)
        assert stack.pid(service) != old
        if produces:
            fault_figures(f"{service}_sigkill_to_{produces.replace('/', '_')}_wall",
                          obs.wait_fresh(produces, dead, timeout_s=60) + dead - killed)
        if service in ("sim", "drive"):
            wait_for_sync(lambda: obs.wheels.link_ok and obs.fresh("wheels", time.monotonic() - 0.5),
                          timeout_s=30, message="drive did not get its controllers back")
            fault_figures(f"{service}_sigkill_to_can_link_ok_wall", time.monotonic() - killed)
    finally:
        obs.streaming(False)
