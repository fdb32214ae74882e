"""SIGKILL of hmi_api during pose writes: every write that was acknowledged is still there after the restart."""

from __future__ import annotations

import os
import re
import signal
import threading

import httpx
import pytest

from tests.support.hmi import HmiClient, base_url, first_run_passwords, hmi_stack, password_of, wait_http
from tests.support.waiting import wait_for_sync

pytestmark = pytest.mark.integration


def test_kill9_loses_no_acknowledged_pose(tmp_path):
    stack = hmi_stack(tmp_path)
    try:
        stack.start()
        wait_http(stack)
        password = password_of(stack)
        acked: dict[int, tuple[str, float]] = {}  # id -> (name, x) as acknowledged
        patched: dict[int, set[float]] = {}  # id -> x values that may be there (last acked, in flight)
        stop = threading.Event()
        lock = threading.Lock()
        writing: set[str] = set()  # writers that logged in and are writing

        def adder(worker: int) -> None:
            with HmiClient(base_url(stack)) as c:
                c.login(password)
                writing.add(f"adder {worker}")
                i = 0
                while not stop.is_set():
                    name = f"w{worker}-{i}"
                    try:
                        r = c.post("/api/poses", json={"name": name, "x": float(i), "y": float(worker), "theta": 0})
                    except httpx.TransportError:
                        return
                    if r.status_code == 201:
                        with lock:
                            acked[r.json()["id"]] = (name, float(i))
                    i += 1

        def patcher() -> None:
            with HmiClient(base_url(stack)) as c:
                c.login(password)
                writing.add("patcher")
                r = c.post("/api/poses", json={"name": "patched", "x": 0.0, "y": 0.0, "theta": 0.0})
                pid = r.json()["id"]
                with lock:
                    acked[pid] = ("patched", 0.0)
                    patched[pid] = {0.0}
                x = 0.0
                while not stop.is_set():
                    x += 1.0
                    with lock:
                        patched[pid].add(x)  # in flight: may or may not have committed
                    try:
                        r = c.patch(f"/api/poses/{pid}", json={"x": x})
                    except httpx.TransportError:
                        return
                    if r.status_code == 200:
                        with lock:
                            patched[pid] = {x}

        threads = [threading.Thread(target=adder, args=(w,)) for w in range(2)] + [threading.Thread(target=patcher)]
        for t in threads:
            t.start()
        wait_for_sync(lambda: len(writing) == len(threads) and len(acked) >= 40, timeout_s=60,
                      message="pose writers did not all start (login refused?) or wrote too slowly")
        victim = stack.pid("hmi_api")
        lines_before = stack.line_count()
        os.kill(victim, signal.SIGKILL)
        for t in threads:
            t.join(timeout=20)
        stop.set()
        # the process hmi_api runs in: its own, or the container it is composed in (zagv up's default)
        stack.wait_line(rf"started {re.escape(stack.process_of('hmi_api'))} \(pid", timeout_s=30, after=lines_before)
        wait_http(stack)
        with HmiClient(base_url(stack)) as c:
            c.login(password)  # the first-run password survives the restart
            stored = {p["id"]: p for p in c.get("/api/poses").json()}
        lost = [pid for pid in acked if pid not in stored]
        assert not lost, f"acknowledged poses lost after SIGKILL: {lost}"
        for pid, (name, x) in acked.items():
            if pid in patched:
                assert stored[pid]["x"] in patched[pid], (stored[pid], patched[pid])
            else:
                assert (stored[pid]["name"], stored[pid]["x"]) == (name, x)
        assert len(first_run_passwords(stack)) == 1  # shown once, not again after the restart
        print(f"\nkill -9 after {len(acked)} acknowledged writes: all {len(acked)} present, "
              f"{len(stored) - len(acked)} unacknowledged ones also committed")
    finally:
        stack.stop()
