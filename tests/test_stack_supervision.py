"""``zagv up`` with real services: restart after SIGKILL, garbage on a subscribed key, ``zagv status``."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import pytest

from proto import encode
from proto.messages import Odometry, Twist2D
from services.launch.stack_process import REPO_ROOT
from tests.support.waiting import wait_for_sync

pytestmark = pytest.mark.integration


def _stats(stack, service: str) -> dict:
    session = stack.session()
    for reply in session.get(stack.keys(f"@stats/{service}"), timeout=2.0):
        if reply.ok is not None:
            return json.loads(reply.ok.payload.to_bytes())
    return {}


def test_killed_service_is_restarted_within_2_s_and_logged(stack_factory):
    stack = stack_factory(services=["sim", "drive"], speed=1.0).start()
    old = stack.pid("drive")
    mark = stack.line_count()
    killed_at = time.monotonic()
    os.kill(old, signal.SIGKILL)
    stack.wait_line(r"^zagv\s+\| drive killed by SIGKILL; restarting", timeout_s=5, after=mark)
    stack.wait_line(r"^zagv\s+\| started drive \(pid \d+\)", timeout_s=5, after=mark)
    restarted_after = time.monotonic() - killed_at
    assert stack.pid("drive") != old
    assert restarted_after <= 2.0, f"restart took {restarted_after:.2f} s"
    stack.wait_line(r"^zagv: drive healthy again", timeout_s=30, after=mark)


def test_garbage_on_a_subscribed_key_is_logged_counted_and_survived(stack_factory):
    stack = stack_factory(services=["sim", "drive"], speed=1.0).start()
    session = stack.session()
    pid = stack.pid("drive")
    raw = session.declare_publisher(stack.keys("cmd_vel"))
    for payload in (b"\x00garbage", encode(Odometry()), b""):
        raw.put(payload)
    wait_for_sync(lambda: sum(_stats(stack, "drive").get("bad_payloads", {}).values()) >= 2, timeout_s=10)
    stack.wait_line(r"^drive\s+\| .*dropped bad payload #\d+ on agv/r1/cmd_vel", timeout_s=5)
    # still serving: a valid command is accepted and the process is the same
    raw.put(encode(Twist2D(vx=0.0)))
    assert stack.pid("drive") == pid
    assert _stats(stack, "drive")["service"] == "drive"


def test_status_lists_healthy_services(stack_factory):
    stack = stack_factory(services=["sim", "drive"], speed=1.0).start()
    proc = subprocess.run([sys.executable, "-m", "services.cli", "status", "--json", "--connect", stack.endpoint],
                          capture_output=True, text=True, cwd=REPO_ROOT, timeout=30)
    report = json.loads(proc.stdout)
    assert report["services"]["drive"]["healthy"] and report["services"]["sim"]["healthy"]
    assert not report["services"]["nav"]["healthy"] or "nav" in stack.output()
