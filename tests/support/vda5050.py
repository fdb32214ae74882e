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
from pathlib import Path
from typing import Any

import paho.mqtt.client as paho
import pytest

from services.common.ports import free_port
from services.scenario.vda5050_master import MASTER_DIR, MasterProcess, MasterUnavailable, install_master
from services.vda5050.schemas import validate


def npm_ready(folder: Path) -> None:
    """``npm ci`` in ``folder`` when its node_modules is missing; skip the test without node/npm."""
    if shutil.which("node") is None or shutil.which("npm") is None:
        pytest.skip("node and npm are needed for the third-party VDA 5050 master control (apt-get install nodejs npm)")
    try:
        install_master(folder)
    except MasterUnavailable as exc:
        pytest.fail(str(exc))


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


class Master(MasterProcess):
    """The third-party master control in a node process (``services/scenario/vda5050_master.py``); skips the test
    without node/npm."""

    def __init__(self, broker_port: int, serial: str | list[str] = "r1", manufacturer: str = "zagv",
                 interface: str = "uagv") -> None:
        npm_ready(MASTER_DIR)
        super().__init__(broker_port, serial, manufacturer, interface)


class Recorder:
    """Subscribes to everything under the vehicle's topic base; validates each vehicle message as it arrives."""

    def __init__(self, port: int, base: str) -> None:
        self.base = base
        self.messages: list[tuple[float, str, bytes]] = []
        self.invalid: list[str] = []
        self.full_topics: set[str] = set()
        self._lock = threading.Lock()
        self.client = paho.Client(paho.CallbackAPIVersion.VERSION2)
        self.client.on_message = self._on_message
        self.client.connect("127.0.0.1", port)
        self.client.subscribe(f"{base}/#")
        self.client.loop_start()

    def _on_message(self, client, userdata, msg) -> None:
        topic = msg.topic.rsplit("/", 1)[-1]
        with self._lock:
            self.full_topics.add(msg.topic)
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

    def topics(self) -> set[str]:
        """Every full topic a message arrived on."""
        with self._lock:
            return set(self.full_topics)

    def count(self, topic: str | None = None) -> int:
        with self._lock:
            return len(self.messages) if topic is None else sum(1 for _, t, _ in self.messages if t == topic)

    def mark(self) -> int:
        with self._lock:
            return len(self.messages)

    def stop(self) -> None:
        self.client.loop_stop()
        self.client.disconnect()
