"""``zagv router`` as a child process of a test: started, stopped and started again, its output kept for failure
reports. The one router class of the tests (the in-process router is the ``router`` fixture of conftest.py)."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
from pathlib import Path

from tests.support.waiting import wait_for_sync

REPO_ROOT = Path(__file__).resolve().parents[2]


class RouterProcess:
    """``python -m services.cli router <args>`` in its own process group; ``lines`` holds its output."""

    def __init__(self, args: list[str], *, port: int | None = None) -> None:
        self.args = args
        self.port = port
        self.endpoint = f"tcp/127.0.0.1:{port}" if port is not None else ""
        self.proc: subprocess.Popen[bytes] | None = None
        self.lines: list[str] = []

    @classmethod
    def listening_on(cls, port: int) -> RouterProcess:
        """A router on one loopback TCP port."""
        return cls(["--listen", f"tcp/127.0.0.1:{port}"], port=port)

    def start(self) -> RouterProcess:
        env = {**os.environ, "PYTHONPATH": str(REPO_ROOT), "PYTHONUNBUFFERED": "1"}
        self.proc = subprocess.Popen([sys.executable, "-m", "services.cli", "router", *self.args],
                                     stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                     cwd=REPO_ROOT, env=env, start_new_session=True)
        threading.Thread(target=self._read, args=(self.proc,), daemon=True).start()
        if self.port is not None:
            wait_for_sync(lambda: self.listening() or not self.running(), timeout_s=20, poll_s=0.01,
                          message="zagv router never listened")
            assert self.running(), f"zagv router exited:\n{self.output()}"
        return self

    def _read(self, proc: subprocess.Popen[bytes]) -> None:
        assert proc.stdout
        for raw in proc.stdout:
            self.lines.append(raw.decode(errors="replace").rstrip())

    def running(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def listening(self) -> bool:
        """Whether the router's TCP port takes a connection."""
        assert self.port is not None
        try:
            with socket.create_connection(("127.0.0.1", self.port), timeout=0.5):
                return True
        except OSError:
            return False

    def output(self) -> str:
        return "\n".join(self.lines[-40:])

    def stop(self) -> None:
        """SIGTERM to the router's process group, SIGKILL after 10 s."""
        if self.proc is None or self.proc.poll() is not None:
            return
        os.killpg(self.proc.pid, signal.SIGTERM)
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait()
