"""VDA 5050 test tools: Debian's mosquitto on a loopback port, the third-party master control (npm vda-5050-lib's
MasterController, ``tests/vda5050_master``) as a node process, and an MQTT recorder that checks every message the
vehicle publishes against the official schemas."""

from __future__ import annotations

import contextlib
import json
import shutil
import subprocess
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import paho.mqtt.client as paho
import pytest

from services.common.ports import free_port
from services.vda5050.schemas import validate

MASTER_DIR = Path(__file__).resolve().parents[1] / "vda5050_master"


def npm_ready(folder: Path) -> None:
    """``npm ci`` in ``folder`` when its node_modules is missing; skip the test without node/npm."""
    if shutil.which("node") is None or shutil.which("npm") is None:
        pytest.skip("node and npm are needed for the third-party VDA 5050 master control (apt-get install nodejs npm)")
    if not (folder / "node_modules").is_dir():
        done = subprocess.run(["npm", "ci", "--no-audit", "--no-fund"], cwd=folder, capture_output=True, text=True,
                              timeout=300)
        if done.returncode != 0:
            pytest.fail(f"npm ci in {folder} failed:\n{done.stdout[-2000:]}\n{done.stderr[-2000:]}")


class Mosquitto:
    """``mosquitto -p PORT`` (loopback only, anonymous): the reference broker."""

    def __init__(self, run_dir: Path) -> None:
        exe = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
        if not Path(exe).exists():
            pytest.skip("Debian's mosquitto is needed as the reference MQTT broker (apt-get install mosquitto)")
        self.port = free_port()
        conf = run_dir / "mosquitto.conf"
        conf.write_text(f"listener {self.port} 127.0.0.1\nallow_anonymous true\npersistence false\n")
        self.log = open(run_dir / "mosquitto.log", "wb")  # noqa: SIM115 - closed in stop()
        self.proc = subprocess.Popen([exe, "-c", str(conf)], stdout=self.log, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + 10
        while True:
            with contextlib.suppress(OSError):
                import socket

                with socket.create_connection(("127.0.0.1", self.port), timeout=0.5):
                    break
            if time.monotonic() > deadline or self.proc.poll() is not None:
                raise AssertionError(f"mosquitto did not listen on {self.port}")
            time.sleep(0.05)

    def stop(self) -> None:
        self.proc.terminate()
        with contextlib.suppress(subprocess.TimeoutExpired):
            self.proc.wait(timeout=5)
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()
        self.log.close()


class Master:
    """The third-party master control in a node process; events are JSON lines (see master.js)."""

    def __init__(self, broker_port: int, serial: str = "r1", manufacturer: str = "zagv",
                 interface: str = "uagv") -> None:
        npm_ready(MASTER_DIR)
        self.proc = subprocess.Popen(["node", "master.js", f"mqtt://127.0.0.1:{broker_port}", interface, manufacturer,
                                      serial], cwd=MASTER_DIR, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, text=True)
        self.events: list[dict[str, Any]] = []
        self.stderr: list[str] = []
        self._lock = threading.Lock()
        threading.Thread(target=self._read, daemon=True).start()
        threading.Thread(target=self._read_err, daemon=True).start()
        self.wait(lambda e: e["event"] == "started", timeout_s=60, what="the master to start")

    def _read(self) -> None:
        assert self.proc.stdout
        for line in self.proc.stdout:
            with contextlib.suppress(json.JSONDecodeError), self._lock:
                self.events.append(json.loads(line))

    def _read_err(self) -> None:
        assert self.proc.stderr
        for line in self.proc.stderr:
            with self._lock:
                self.stderr.append(line.rstrip("\n"))

    def send(self, command: dict[str, Any]) -> int:
        """Send a command; returns the event index to search from for its consequences."""
        with self._lock:
            mark = len(self.events)
        assert self.proc.stdin
        self.proc.stdin.write(json.dumps(command) + "\n")
        self.proc.stdin.flush()
        return mark

    def find(self, pred: Callable[[dict[str, Any]], bool], after: int = 0) -> dict[str, Any] | None:
        with self._lock:
            return next((e for e in self.events[after:] if pred(e)), None)

    def all(self, pred: Callable[[dict[str, Any]], bool], after: int = 0) -> list[dict[str, Any]]:
        with self._lock:
            return [e for e in self.events[after:] if pred(e)]

    def mark(self) -> int:
        with self._lock:
            return len(self.events)

    def wait(self, pred: Callable[[dict[str, Any]], bool], *, timeout_s: float, after: int = 0,
             what: str = "") -> dict[str, Any]:
        deadline = time.monotonic() + timeout_s
        while True:
            found = self.find(pred, after)
            if found is not None:
                return found
            if self.proc.poll() is not None or time.monotonic() > deadline:
                with self._lock:
                    tail = self.events[-8:]
                raise AssertionError(f"master: no {what or 'matching event'} within {timeout_s} s; last events: "
                                     f"{json.dumps(tail)[-3000:]}; stderr: {self.stderr[-5:]}")
            time.sleep(0.02)

    def last_state(self) -> dict[str, Any] | None:
        with self._lock:
            return next((e for e in reversed(self.events) if e["event"] == "state"), None)

    def stop(self) -> None:
        if self.proc.poll() is None:
            with contextlib.suppress(BrokenPipeError, OSError):
                self.send({"cmd": "stop"})
            try:
                self.proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


class Recorder:
    """Subscribes to everything under the vehicle's topic base; validates each vehicle message as it arrives."""

    def __init__(self, port: int, base: str) -> None:
        self.base = base
        self.messages: list[tuple[float, str, bytes]] = []
        self.invalid: list[str] = []
        self._lock = threading.Lock()
        self.client = paho.Client(paho.CallbackAPIVersion.VERSION2)
        self.client.on_message = self._on_message
        self.client.connect("127.0.0.1", port)
        self.client.subscribe(f"{base}/#")
        self.client.loop_start()

    def _on_message(self, client, userdata, msg) -> None:
        topic = msg.topic.rsplit("/", 1)[-1]
        with self._lock:
            self.messages.append((time.monotonic(), topic, bytes(msg.payload)))
            if topic in ("state", "visualization", "connection", "factsheet"):
                try:
                    problems = validate(topic, json.loads(msg.payload))
                except json.JSONDecodeError as exc:
                    problems = [f"not JSON: {exc}"]
                if problems:
                    self.invalid.append(f"{topic}: {problems}")

    def publish(self, topic: str, payload: bytes) -> None:
        self.client.publish(f"{self.base}/{topic}", payload).wait_for_publish(5)

    def states(self, after: int = 0) -> list[dict[str, Any]]:
        with self._lock:
            return [json.loads(p) for _, t, p in self.messages[after:] if t == "state"]

    def count(self, topic: str | None = None) -> int:
        with self._lock:
            return len(self.messages) if topic is None else sum(1 for _, t, _ in self.messages if t == topic)

    def mark(self) -> int:
        with self._lock:
            return len(self.messages)

    def stop(self) -> None:
        self.client.loop_stop()
        self.client.disconnect()
