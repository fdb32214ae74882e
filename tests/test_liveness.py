"""A service whose event loop hangs in a blocking call: its health token goes, it kills itself to be restarted,
it dies with its supervisor even when it cannot run a signal handler, and ``zagv up`` stops within 10 s of Ctrl-C
leaving no process behind."""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import textwrap
import threading
import time
from pathlib import Path

import pytest

from proto.keys import Keys
from services.common.session import open_session
from services.common.settings import ZenohSettings
from services.launch.stack_process import REPO_ROOT, Stack
from tests.support.processes import process_alive
from tests.support.waiting import wait_for_sync

#: a service that answers for a moment, then blocks its event loop in a read that never returns (like a read of
#: /dev/zero or of a FIFO nobody writes)
HANGING_SERVICE = textwrap.dedent("""
    import asyncio, os, sys
    from services.common.service import service_main

    async def run(ctx):
        ctx.node.ready()  # the health token (docs/readiness.md)
        await asyncio.sleep(1.0)
        print("hanging now", flush=True)
        read_end, _write_end = os.pipe()
        os.read(read_end, 1)

    service_main("hangs", {}, run, sys.argv[1:])
""")



@pytest.mark.integration
def test_hung_loop_withdraws_its_health_token_then_kills_itself(router: str) -> None:
    session = open_session(ZenohSettings(mode="client", connect=[router]))
    health = Keys("r1").health("hangs")

    def healthy() -> bool:
        return any(r.ok is not None for r in session.liveliness().get(health, timeout=1.0))

    proc = subprocess.Popen([sys.executable, "-c", HANGING_SERVICE, "--connect", router,
                             "--set", "liveness.stall_s=1.0", "--set", "liveness.kill_s=4.0"],
                            cwd=REPO_ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        wait_for_sync(healthy, timeout_s=20, message="the service never declared its health token")
        assert proc.stdout is not None
        while "hanging now" not in (line := proc.stdout.readline()):
            assert line, "the service ended before hanging"
        hung_at = time.monotonic()
        wait_for_sync(lambda: not healthy(), timeout_s=10, message="a hung service stayed healthy")
        token_gone_s = time.monotonic() - hung_at
        code = proc.wait(timeout=20)
        dead_s = time.monotonic() - hung_at
        output = proc.stdout.read()
    finally:
        if proc.poll() is None:
            proc.kill()
        session.close()
    print(f"\nliveness: token withdrawn {token_gone_s:.2f} s and process killed {dead_s:.2f} s after the hang")
    assert code == -signal.SIGKILL, output
    assert "health token withdrawn" in output and "killing the process" in output, output
    assert token_gone_s < 4.0 + 2.0  # withdrawn at stall_s, well before the kill


def test_child_dies_with_its_supervisor_even_blocked_with_sigterm_ignored(tmp_path: Path) -> None:
    child = textwrap.dedent("""
        import os, signal
        from services.common.lifetime import die_with_parent
        die_with_parent()
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        print(os.getpid(), flush=True)
        read_end, _ = os.pipe()
        os.read(read_end, 1)
    """)
    parent = textwrap.dedent(f"""
        import os, subprocess, sys, time
        env = dict(os.environ, ZAGV_PARENT_PID=str(os.getpid()))
        subprocess.Popen([sys.executable, "-c", {child!r}], env=env)
        time.sleep(600)
    """)
    proc = subprocess.Popen([sys.executable, "-c", parent], cwd=REPO_ROOT, stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        child_pid = int(proc.stdout.readline())
        assert process_alive(child_pid)
    finally:
        proc.kill()
        proc.wait()
    wait_for_sync(lambda: not process_alive(child_pid), timeout_s=5,
                  message="the child outlived its supervisor (blocked, SIGTERM ignored)")


@pytest.mark.integration
def test_zagv_up_stops_within_10_s_of_ctrl_c_with_a_stopped_service(tmp_path: Path) -> None:
    stack = Stack(tmp_path, ["sim", "drive"], world="empty_room")
    stack.start()
    try:
        pids = {name: stack.pid(name) for name in ("sim", "canbus", "drive")}
        os.kill(pids["drive"], signal.SIGSTOP)  # runs no handler at all, as one blocked in the kernel
        assert stack.proc is not None
        stopped_at = time.monotonic()
        stack.proc.send_signal(signal.SIGINT)
        stack.proc.wait(timeout=30)
        took_s = time.monotonic() - stopped_at
    finally:
        stack.stop()
    print(f"\nzagv up stopped {took_s:.2f} s after Ctrl-C with drive stopped (SIGSTOP)")
    assert took_s <= 10.0
    left = [name for name, pid in pids.items() if process_alive(pid)]
    assert not left, f"left behind: {left}"


@pytest.mark.integration
def test_hung_loop_stops_the_systemd_watchdog_keepalives(router: str) -> None:
    """What WatchdogSec in the service units relies on: WATCHDOG=1 comes from the event loop, so a blocked loop
    stops it and systemd restarts the unit (the service also kills itself at the limit)."""
    sock_dir = Path(tempfile.mkdtemp(prefix="zagv-notify-"))  # AF_UNIX paths are limited to 108 bytes
    received: list[tuple[float, str]] = []
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind(str(sock_dir / "notify"))
        sock.settimeout(0.05)
        env = {**os.environ, "NOTIFY_SOCKET": str(sock_dir / "notify"), "WATCHDOG_USEC": "2000000"}
        env.pop("WATCHDOG_PID", None)
        proc = subprocess.Popen([sys.executable, "-c", HANGING_SERVICE, "--connect", router,
                                 "--set", "liveness.stall_s=1.0"], cwd=REPO_ROOT, env=env,
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        hung_at: list[float] = []

        def read_output() -> None:
            assert proc.stdout is not None
            for line in proc.stdout:
                if "hanging now" in line:
                    hung_at.append(time.monotonic())

        threading.Thread(target=read_output, daemon=True).start()
        try:
            while proc.poll() is None:
                with contextlib.suppress(TimeoutError):
                    received.append((time.monotonic(), sock.recv(256).decode()))
            code = proc.wait()
        finally:
            if proc.poll() is None:
                proc.kill()
    shutil.rmtree(sock_dir, ignore_errors=True)
    assert hung_at, "the service never hung"
    feeds = [t for t, text in received if text == "WATCHDOG=1"]
    assert [text for _, text in received][:1] == ["READY=1"] and feeds
    assert all(t < hung_at[0] + 0.5 for t in feeds), "keep-alives went on while the loop was blocked"
    assert code == -signal.SIGKILL  # killed at WatchdogSec by its own watchdog, as systemd would


def test_a_service_sharing_its_loop_takes_the_longest_default_limits_of_the_loop() -> None:
    from services.common.liveness import DEFAULT_LIMITS_S, LivenessLimits

    alone = LivenessLimits.for_service("nav")
    shared = LivenessLimits.for_service("nav", loop_mates=["localization", "recorder"])
    assert (alone.stall_s, alone.kill_s) == DEFAULT_LIMITS_S["nav"]
    assert (shared.stall_s, shared.kill_s) == DEFAULT_LIMITS_S["localization"]
    # a [liveness] table's own figures still win
    assert LivenessLimits.for_service("nav", 2.0, 4.0, ["localization"]).kill_s == 4.0
