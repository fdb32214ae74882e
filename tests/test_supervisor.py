"""The supervisor restarts a killed child quickly, logs the exit, and leaves no orphan."""

from __future__ import annotations

import signal
import sys

from services.launch.supervisor import ChildSpec, Supervisor
from tests.support.processes import process_alive
from tests.support.waiting import wait_for

SLEEPER = [sys.executable, "-c", "import time; print('child up', flush=True); time.sleep(600)"]



async def test_killed_child_is_restarted_and_logged():
    lines: list[str] = []
    sup = Supervisor(out=lines.append)
    state = sup.add(ChildSpec("worker", SLEEPER))
    await wait_for(lambda: state.pid and any("child up" in x for x in lines), timeout_s=10)
    first = state.pid
    sup.kill("worker", signal.SIGKILL)
    await wait_for(lambda: state.pid and state.pid != first, timeout_s=2.0,
                   message="child not restarted within 2 s")
    assert any("worker killed by SIGKILL; restarting" in x for x in lines), lines
    await wait_for(lambda: sum("child up" in x for x in lines) == 2, timeout_s=10)
    second = state.pid
    await sup.stop()
    assert not process_alive(first) and not process_alive(second)
    assert all(line.startswith(("worker", "zagv")) for line in lines)


async def test_child_that_ignores_sigterm_is_killed_on_stop():
    lines: list[str] = []
    sup = Supervisor(out=lines.append)
    code = ("import signal, time; signal.signal(signal.SIGTERM, signal.SIG_IGN); "
            "print('up', flush=True); time.sleep(600)")
    state = sup.add(ChildSpec("stubborn", [sys.executable, "-c", code]))
    await wait_for(lambda: any(" up" in x for x in lines), timeout_s=10)
    pid = state.pid
    await sup.stop(timeout_s=0.5)
    assert pid is not None and not process_alive(pid)
