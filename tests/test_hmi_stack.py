"""hmi_api's robot endpoints against the whole simulated stack (skipped until every robot service exists).

enable / estop / release, jog moving the robot and stopping by itself, initial pose, goal, cancel, home,
the map from localization, and the pose list run as a waypoint sequence.
"""

from __future__ import annotations

import math
import time

import pytest

from tests.support.hmi import (
    HmiClient,
    base_url,
    full_stack_available,
    hmi_stack,
    missing_services,
    password_of,
    wait_http,
)
from tests.support.waiting import wait_for_sync

pytestmark = [
    pytest.mark.integration, pytest.mark.slow,
    pytest.mark.skipif(not full_stack_available(),
                       reason=f"needs the simulated stack; missing services: {', '.join(missing_services())}"),
]


@pytest.fixture(scope="module")
def robot(tmp_path_factory):
    stack = hmi_stack(tmp_path_factory.mktemp("hmi_stack"), full=True)
    try:
        stack.start(ready_timeout_s=120)
        wait_http(stack)
        with HmiClient(base_url(stack)) as client:
            client.login(password_of(stack))
            wait_for_sync(lambda: client.get("/api/status").json()["pose"] is not None, timeout_s=60,
                          message="no map pose from localization")
            wait_for_sync(lambda: (client.get("/api/status").json()["wheels"] or {}).get("link_ok"), timeout_s=60,
                          message="drive never reached the controllers")
            yield stack, client
    finally:
        stack.stop()


def status(client):
    return client.get("/api/status").json()


def test_map_from_localization(robot):
    _, client = robot
    m = wait_for_sync(lambda: (lambda j: j if j["available"] else None)(client.get("/api/map").json()), timeout_s=30)
    assert m["width"] > 100 and m["resolution_m"] > 0 and m["png_base64"]


def test_enable_jog_estop_release(robot):
    _, client = robot
    r = client.post("/api/drive/enable")
    assert r.status_code == 200, r.text
    wait_for_sync(lambda: (status(client)["wheels"] or {}).get("enabled"), timeout_s=20, message="drive not enabled")
    x0 = status(client)["odom"]["x"]
    deadline = time.monotonic() + 30
    while status(client)["odom"]["x"] < x0 + 0.05:
        assert time.monotonic() < deadline, "jog did not move the robot"
        assert client.post("/api/jog", json={"vx": 0.15}).status_code == 200
        time.sleep(0.1)
    # the dead-man: with no more jog requests, the robot comes to rest by itself
    wait_for_sync(lambda: abs(status(client)["odom"]["vx"] or 0.0) < 0.01, timeout_s=20,
                  message="the robot kept moving after the jog requests stopped")
    assert client.post("/api/drive/estop").status_code == 200
    wait_for_sync(lambda: (status(client)["wheels"] or {}).get("estopped"), timeout_s=10)
    assert client.post("/api/drive/release").status_code == 200
    assert client.post("/api/drive/enable").status_code == 200


def test_goal_cancel_home_and_initial_pose(robot):
    _, client = robot
    client.post("/api/drive/enable")
    p = status(client)["pose"]
    assert client.post("/api/initial_pose", json={"x": p["x"], "y": p["y"], "theta": p["theta"]}).status_code == 200
    r = client.post("/api/goal", json={"x": 2.0, "y": 0.3, "theta": 0.0})
    assert r.status_code == 200 and r.json()["accepted"], r.text
    wait_for_sync(lambda: status(client)["nav"]["state"] in ("planning", "driving", "rotating"), timeout_s=20)
    assert client.post("/api/goal/cancel").status_code == 200
    wait_for_sync(lambda: status(client)["nav"]["state"] in ("canceled", "idle"), timeout_s=20)
    r = client.post("/api/home")
    assert r.status_code == 200 and r.json()["goal_id"], r.text

    def home() -> bool:
        s = status(client)
        return s["nav"]["state"] == "succeeded" and math.hypot(s["pose"]["x"], s["pose"]["y"]) < 0.1

    wait_for_sync(home, timeout_s=120, poll_s=0.2, message="home not reached")


def test_run_pose_list_as_waypoints(robot):
    _, client = robot
    client.post("/api/drive/enable")
    for p in client.get("/api/poses").json():
        client.delete(f"/api/poses/{p['id']}")
    client.post("/api/poses", json={"name": "a", "x": 1.5, "y": 0.0, "theta": 0.0})
    client.post("/api/poses", json={"name": "b", "x": 1.5, "y": 0.6, "theta": 1.57})
    r = client.post("/api/poses/run")
    assert r.status_code == 200 and r.json()["accepted"], r.text
    wait_for_sync(lambda: status(client)["nav"]["waypoint_count"] == 2, timeout_s=20)

    def done() -> bool:
        s = status(client)
        return s["nav"]["state"] == "succeeded" and math.hypot(s["pose"]["x"] - 1.5, s["pose"]["y"] - 0.6) < 0.1

    wait_for_sync(done, timeout_s=180, poll_s=0.2, message="the pose list was not run to its end")
