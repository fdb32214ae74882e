"""Helpers for hmi_api tests: a logged-in HTTP client, and whether the full simulated stack exists."""

from __future__ import annotations

import importlib.util
import re
import time
from pathlib import Path

import httpx

from tests.support.stack import Stack
from tests.support.waiting import wait_for_sync

ROBOT_SERVICES = ["sim", "drive", "lidar", "localization", "nav"]
PASSWORD_LINE = r"first-run password: (\S+)"


def full_stack_available() -> bool:
    """True once every robot service (sim, drive, lidar, localization, nav) has a ``__main__``."""
    return all(importlib.util.find_spec(f"services.{s}.__main__") is not None for s in ROBOT_SERVICES)


def missing_services() -> list[str]:
    return [s for s in ROBOT_SERVICES if importlib.util.find_spec(f"services.{s}.__main__") is None]


class HmiClient(httpx.Client):
    """httpx client on the stack's HMI port; ``login()`` stores the bearer token in its headers."""

    def __init__(self, base_url: str) -> None:
        super().__init__(base_url=base_url, timeout=15.0)
        self.token = ""

    def login(self, password: str, timeout_s: float = 30.0) -> str:
        """Log in; a 429 while another login from this host is being checked is retried until ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        r = self.post("/api/login", json={"password": password})
        while r.status_code == 429 and "being checked" in r.text and time.monotonic() < deadline:
            time.sleep(min(float(r.headers.get("retry-after", "0.2")), 0.2))
            r = self.post("/api/login", json={"password": password})
        assert r.status_code == 200, r.text
        self.token = r.json()["token"]
        self.headers["authorization"] = f"Bearer {self.token}"
        return self.token


def hmi_stack(run_dir: Path, *, full: bool = False, sets: list[str] | None = None, speed: float = 1.0) -> Stack:
    """A stack with hmi_api alone (wall clock) or the whole simulated robot; not started yet."""
    extra = [a for s in (sets or []) for a in ("--set", s)]
    if full:
        return Stack(run_dir, None, sim=True, speed=speed, extra_args=extra)
    return Stack(run_dir, ["hmi_api"], sim=False, extra_args=extra)


def wait_http(stack: Stack, timeout_s: float = 20.0) -> None:
    """Wait until the HMI answers HTTP (its health token may come up a moment before it listens)."""

    def answers() -> bool:
        try:
            return httpx.get(base_url(stack) + "/", timeout=2.0).status_code == 200
        except httpx.TransportError:
            return False

    wait_for_sync(answers, timeout_s=timeout_s, poll_s=0.05, message="the HMI never answered HTTP")


def password_of(stack: Stack, timeout_s: float = 20.0) -> str:
    return stack.wait_line(PASSWORD_LINE, timeout_s=timeout_s).group(1)


def base_url(stack: Stack) -> str:
    return f"http://127.0.0.1:{stack.http_port}"


def first_run_passwords(stack: Stack) -> list[str]:
    return re.findall(PASSWORD_LINE, stack.output())
