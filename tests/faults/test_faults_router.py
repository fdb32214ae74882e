"""The Zenoh router stopped and restarted under a running stack (``zagv up --external-router`` + ``zagv router``).

Every service keeps running, gets its health token back and its data flows again once the router is back.
"""

from __future__ import annotations

import re
import time
from collections.abc import Iterator

import pytest

from services.common.ports import free_port
from services.launch.stack_process import Stack
from tests.faults.test_faults_services import Observer
from tests.support.router import RouterProcess

pytestmark = pytest.mark.integration

SERVICES = ["sim", "drive", "lidar", "localization", "nav", "hmi_api"]
DATA = ["clock", "wheels", "scan", "tf/map_odom"]


@pytest.fixture
def routed(tmp_path) -> Iterator[tuple[RouterProcess, Stack, Observer]]:
    router = RouterProcess.listening_on(free_port()).start()
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    stack = Stack(run_dir, SERVICES, world="corridor", speed=1.0, extra_args=["--external-router", router.endpoint])
    stack.endpoint = router.endpoint
    observer = None
    try:
        stack.start()
        observer = Observer(stack)
        yield router, stack, observer
    finally:
        if observer:
            observer.close()
        stack.stop()
        router.stop()


def test_router_restart_every_service_reconnects(routed, fault_figures) -> None:
    router, stack, obs = routed
    now = time.monotonic()
    for name in DATA:
        obs.wait_fresh(name, now, timeout_s=60)
    pids = {s: stack.pid(s) for s in SERVICES}
    mark = stack.line_count()
    router.stop()
    for s in SERVICES:  # zagv up's own session sees the tokens go with the router
        stack.wait_line(rf"^zagv: {s} lost its health token", timeout_s=30, after=mark)
    mark = stack.line_count()
    gone = time.monotonic()
    router.start()
    restarted = time.monotonic()  # the new router accepts connections: figures below count from here
    fault_figures("router_start_to_listening_wall", restarted - gone)
    back: dict[str, float] = {}
    deadline = time.monotonic() + 60
    while len(back) < len(SERVICES) + len(DATA) and time.monotonic() < deadline:
        lines = stack.output().splitlines()[mark:]
        for s in SERVICES:
            if s not in back and any(re.match(rf"^zagv: {s} healthy again", line) for line in lines):
                back[s] = time.monotonic() - restarted
        for name in DATA:
            if name not in back and obs.fresh(name, restarted):
                back[name] = obs.last_wall[name] - restarted
        time.sleep(0.02)
    missing = sorted(set(SERVICES + DATA) - set(back))
    assert not missing, f"not back within 60 s of the router restart: {missing}"
    for name, t in sorted(back.items()):
        fault_figures(f"router_restart_to_{name.replace('/', '_')}_wall", t)
    fault_figures("router_restart_to_all_services_reconnected_wall", max(back[s] for s in SERVICES))
    fault_figures("router_restart_to_all_data_flowing_wall", max(back[n] for n in DATA))
    assert {s: stack.pid(s) for s in SERVICES} == pids, "a service restarted instead of reconnecting"
