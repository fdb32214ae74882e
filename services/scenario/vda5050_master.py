"""A third-party VDA 5050 2.0 master control in a node process: npm ``vda-5050-lib``'s MasterController, pinned in
``tests/vda5050_master`` (package.json + lock; ``master.js`` speaks JSON lines on stdin/stdout).

Used by the VDA 5050 fleet scenarios (``zagv scenario run`` of a file with ``[vda5050]``) and the tests. One
process can master several AGVs of one manufacturer (``serials``); every event names its AGV's ``serialNumber``.
"""

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

MASTER_DIR = Path(__file__).resolve().parents[2] / "tests" / "vda5050_master"


class MasterUnavailable(RuntimeError):
    """node/npm are missing or the pinned master control cannot be installed."""


def install_master(folder: Path = MASTER_DIR) -> None:
    """``npm ci`` in ``folder`` when its node_modules is missing (the lock file pins vda-5050-lib)."""
    if shutil.which("node") is None or shutil.which("npm") is None:
        raise MasterUnavailable("node and npm are needed for the third-party VDA 5050 master control "
                                "(apt-get install nodejs npm)")
    if (folder / "node_modules").is_dir():
        return
    done = subprocess.run(["npm", "ci", "--no-audit", "--no-fund"], cwd=folder, capture_output=True, text=True,
                          timeout=300)
    if done.returncode != 0:
        raise MasterUnavailable(f"npm ci in {folder} failed:\n{done.stdout[-2000:]}\n{done.stderr[-2000:]}")


class MasterProcess:
    """``node master.js``; its events (JSON lines, each with the wall time ``t`` in ms) are kept in order."""

    def __init__(self, broker_port: int, serials: str | list[str] = "r1", manufacturer: str = "zagv",
                 interface: str = "uagv", broker_host: str = "127.0.0.1") -> None:
        serial_list = [serials] if isinstance(serials, str) else list(serials)
        self.serials = serial_list
        self.proc = subprocess.Popen(["node", "master.js", f"mqtt://{broker_host}:{broker_port}", interface,
                                      manufacturer, ",".join(serial_list)], cwd=MASTER_DIR, stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self.events: list[dict[str, Any]] = []
        self.stderr: list[str] = []
        self._lock = threading.Lock()
        threading.Thread(target=self._read, daemon=True).start()
        threading.Thread(target=self._read_err, daemon=True).start()
        try:
            self.wait(lambda e: e["event"] == "started", timeout_s=60, what="the master to start")
        except AssertionError:
            self.stop()
            raise

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
        """The first event from ``after`` on that satisfies ``pred``; AssertionError (with the last events) when none
        comes within ``timeout_s`` or the master exits."""
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

    def last_state(self, serial: str | None = None) -> dict[str, Any] | None:
        with self._lock:
            return next((e for e in reversed(self.events) if e["event"] == "state"
                         and (serial is None or e.get("serialNumber") == serial)), None)

    def stop(self) -> None:
        if self.proc.poll() is None:
            with contextlib.suppress(BrokenPipeError, OSError):
                self.send({"cmd": "stop"})
            try:
                self.proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
