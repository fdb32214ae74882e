"""The hmi_api contract against the real service (``zagv up --only hmi_api`` on free loopback ports).

The test plays the robot's other services by publishing real proto messages on the stack's Zenoh router, so the
status, map, WebSocket and teach paths are checked without the simulator. Endpoints that need a robot service
answer 503 here, naming the service; with the full simulated stack they are covered by test_hmi_stack.py.
"""

from __future__ import annotations

import base64
import io
import json
import math
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
from PIL import Image
from websockets.exceptions import ConnectionClosed, InvalidStatus
from websockets.sync.client import connect as ws_connect

from proto import codec
from proto.messages import LaserScan, NavStatus, OccupancyGrid, Odometry, Pose2D, PoseWithCovariance, Twist2D
from services.hmi_api import auth
from tests.support.hmi import HmiClient, base_url, first_run_passwords, hmi_stack, password_of, wait_http
from tests.support.waiting import wait_for_sync

pytestmark = pytest.mark.integration

MOTION_ENDPOINTS = [
    ("POST", "/api/drive/enable"), ("POST", "/api/drive/disable"), ("POST", "/api/drive/estop"),
    ("POST", "/api/drive/release"), ("POST", "/api/jog"), ("POST", "/api/goal"), ("POST", "/api/goal/cancel"),
    ("POST", "/api/home"), ("POST", "/api/initial_pose"), ("POST", "/api/poses/1/send"), ("POST", "/api/poses/run"),
]


@pytest.fixture(scope="module")
def hmi(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("hmi")
    stack = hmi_stack(run_dir, sets=["hmi_api.query_timeout_s=0.5"])
    try:
        stack.start()
        wait_http(stack)
        with HmiClient(base_url(stack)) as client:
            client.login(password_of(stack))
            yield stack, client, stack.session()
    finally:
        stack.stop()


def put(session, stack, name, msg):
    session.put(stack.keys(name), codec.encode(msg))


def test_login_and_openapi(hmi):
    stack, client, _ = hmi
    anon = HmiClient(base_url(stack))
    r = anon.post("/api/login", json={"password": "not it"})
    assert r.status_code == 401 and r.headers["www-authenticate"].startswith("Bearer")
    assert anon.post("/api/login", json={"pass": "x"}).status_code == 422
    assert anon.get("/api/schema/openapi.json").status_code == 401  # the API description is behind login too
    doc = client.get("/api/schema/openapi.json").json()
    assert doc["openapi"].startswith("3.")
    for _, path in MOTION_ENDPOINTS:
        templ = path.replace("/1/", "/{pose_id}/")
        assert templ in doc["paths"], path
    r = anon.get("/")
    assert r.status_code == 200 and "<title>zagv HMI</title>" in r.text
    assert client.get("/api/status").status_code == 200
    r = client.post("/api/logout")
    assert r.status_code == 200
    assert client.get("/api/status").status_code == 401
    client.login(password_of(stack))


def test_every_endpoint_but_login_needs_a_token(hmi):
    stack, client, _ = hmi
    anon = HmiClient(base_url(stack))
    doc = client.get("/api/schema/openapi.json").json()
    checked = []
    for path, methods in doc["paths"].items():
        for method in methods:
            if path == "/api/login":
                continue
            url = path.replace("{pose_id}", "1")
            r = anon.request(method.upper(), url, json={})
            assert r.status_code == 401, (method, path, r.status_code, r.text)
            r = anon.request(method.upper(), url, json={}, headers={"authorization": "Bearer forged"})
            assert r.status_code == 401, (method, path)
            checked.append((method.upper(), url))
    for method, url in MOTION_ENDPOINTS:
        assert anon.request(method, url, json={"vx": 0.1}).status_code == 401, url
    assert len(checked) >= 20


@pytest.mark.parametrize("body", [
    b'{"vx": NaN}', b'{"vx": Infinity}', b'{"vx": 1e999}', b'{"vx": "0.1"}', b'{"vx": true}', b'{"vx": null}',
    b'{"vx": 0.1, "speed": 1}', b'[0.1, 0, 0]', b'not json', b'{"vx": [1]}',
])
def test_jog_rejects_bad_bodies_with_422(hmi, body):
    _, client, _ = hmi
    r = client.post("/api/jog", content=body, headers={"content-type": "application/json"})
    assert r.status_code == 422, r.text
    assert r.json()["detail"]


def test_goal_bodies_are_validated(hmi):
    _, client, _ = hmi
    r = client.post("/api/goal", json={"x": 1.0})
    assert r.status_code == 422 and "y" in r.text
    r = client.post("/api/initial_pose", json={"x": 1.0, "y": "north", "theta": 0})
    assert r.status_code == 422 and "y" in r.text
    r = client.post("/api/poses", json={"name": "p", "x": 1.0, "y": 2.0})
    assert r.status_code == 422 and "theta" in r.text
    r = client.post("/api/poses/1/move", json={"direction": "left"})
    assert r.status_code == 422


def test_robot_endpoints_answer_503_naming_the_missing_service(hmi):
    _, client, _ = hmi
    r = client.post("/api/drive/enable")
    assert r.status_code == 503 and "drive/enable" in r.json()["detail"]
    r = client.post("/api/goal", json={"x": 1.0, "y": 2.0, "theta": 0.0})
    assert r.status_code == 503 and "nav/goal" in r.json()["detail"]
    assert client.post("/api/drive/launch").status_code == 404


def test_jog_is_clamped_published_and_dead_man_stops_it(hmi):
    stack, client, session = hmi
    got: list[tuple[float, Twist2D]] = []
    lock = threading.Lock()

    def on_sample(sample):
        with lock:
            got.append((time.monotonic(), codec.decode("cmd_vel", sample.payload.to_bytes())))

    sub = session.declare_subscriber(stack.keys("cmd_vel"), on_sample)
    try:
        r = client.post("/api/jog", json={"vx": 1.0, "vy": -0.05, "wz": -3.0})
        assert r.status_code == 200
        body = r.json()
        assert (body["vx"], body["vy"], body["wz"], body["clamped"]) == (0.2, -0.05, -0.5, True)
        last_jog = time.monotonic()
        for _ in range(8):  # keep jogging for about 0.8 s, like a held button
            client.post("/api/jog", json={"vx": 1.0, "vy": -0.05, "wz": -3.0})
            last_jog = time.monotonic()
            time.sleep(0.1)
        wait_for_sync(lambda: any(t.vx == 0.0 and t.wz == 0.0 for _, t in got), timeout_s=5,
                      message="no zero twist after the jog stopped")
        time.sleep(0.3)  # the zero repeats are 50 ms apart; after them the gate falls silent
        with lock:
            seen = list(got)
        moving = [t for _, t in seen if t.vx != 0.0]
        first_zero = next(ts for ts, t in seen if t.vx == 0.0 and t.wz == 0.0)
        # on a loaded machine a gap between two held requests can outlast the dead-man time: zeros in between are
        # then right; what must hold is that everything after the last moving twist is zero
        last_moving = max(i for i, (_, t) in enumerate(seen) if t.vx != 0.0)
        tail = seen[last_moving + 1:]
        assert len(moving) >= 5
        assert all((t.vx, t.vy, t.wz) == pytest.approx((0.2, -0.05, -0.5)) for t in moving)
        assert tail and all((t.vx, t.vy, t.wz) == (0.0, 0.0, 0.0) for _, t in tail)
        time.sleep(0.5)  # silence: nothing more is published once the zeros are out
        assert len(got) == len(seen)
        print(f"\njog: {len(moving)} twists while held, {len(tail)} zeros; first zero "
              f"{first_zero - last_jog:.3f} s after the last request")
    finally:
        sub.undeclare()


def test_status_map_and_websocket_from_robot_messages(hmi):
    stack, client, session = hmi
    grid = np.zeros((40, 60), dtype=np.int8)
    grid[0, :] = 100
    grid[:, 59] = -1
    put(session, stack, "map", OccupancyGrid(width=60, height=40, resolution=0.05, origin=Pose2D(x=-1.0, y=-0.5),
                                             data=grid.tobytes()))
    odom = Odometry(pose=Pose2D(x=0.5, y=0.25, theta=0.1), twist=Twist2D(vx=0.1, vy=math.nan, wz=0.0))
    put(session, stack, "odom", odom)
    put(session, stack, "pose", PoseWithCovariance(pose=Pose2D(x=0.5, y=0.25, theta=0.1),
                                                   covariance=[0.01, 0, 0, 0, 0.01, 0, 0, 0, 0.02]))
    put(session, stack, "nav/status", NavStatus(state="idle"))
    ranges = np.full(181, 2.0, dtype="<f4")
    ranges[::10] = np.inf
    put(session, stack, "scan", LaserScan(angle_min=-math.pi / 2, angle_max=math.pi / 2,
                                          angle_increment=math.pi / 180, range_min=0.05, range_max=20.0,
                                          ranges=ranges.tobytes()))

    def status():
        s = client.get("/api/status").json()
        # "pose" is the odom-frame pose until localization's message arrives, so wait for the map frame
        ready = s["odom"] and s["pose"] and s["pose"]["frame"] == "map" and s["nav"] and s["map"]["available"]
        return s if ready else None

    s = wait_for_sync(status, timeout_s=10, message="status never showed the published messages")
    assert s["odom"]["x"] == 0.5 and s["odom"]["vy"] is None  # NaN travels as null
    assert s["pose"]["frame"] == "map" and s["nav"]["state"] == "idle" and "hmi_api" in s["health"]
    raw = client.get("/api/status").content
    assert b"NaN" not in raw and b"Infinity" not in raw
    m = client.get("/api/map").json()
    assert (m["width"], m["height"], m["resolution_m"], m["origin"]["x"]) == (60, 40, 0.05, -1.0)
    img = np.array(Image.open(io.BytesIO(base64.b64decode(m["png_base64"]))))
    assert img.shape == (40, 60) and img[-1, 0] == 0 and img[0, 0] == 254 and img[5, 59] == 205
    assert client.get("/api/map.png").headers["content-type"] == "image/png"

    taught = client.post("/api/poses", json={"name": "here", "from_current": True})
    assert taught.status_code == 201 and (taught.json()["x"], taught.json()["y"]) == (0.5, 0.25)
    client.delete(f"/api/poses/{taught.json()['id']}")

    with pytest.raises((InvalidStatus, ConnectionClosed)), \
            ws_connect(f"ws://127.0.0.1:{stack.http_port}/api/ws", open_timeout=5) as ws:
        ws.recv(timeout=2)  # refused without a token
    url = f"ws://127.0.0.1:{stack.http_port}/api/ws?token={client.token}"
    frames = []
    with ws_connect(url, open_timeout=5) as ws:
        start = time.monotonic()
        while len(frames) < 20:
            frames.append(json.loads(ws.recv(timeout=5)))
        elapsed = time.monotonic() - start
    print(f"\nws: {len(frames) - 1} frames in {elapsed:.2f} s = {(len(frames) - 1) / elapsed:.1f} Hz")
    first = frames[0]
    assert first["type"] == "tick" and "paths" in first and "particles" in first
    assert first["status"]["odom"]["x"] == 0.5
    assert len(first["scan"]) == 2 * (181 - 19)  # the inf beams are left out
    assert all(f["status"]["stamp"] for f in frames)


def test_pose_database_crud_order_export_import(hmi):
    _, client, _ = hmi
    for p in client.get("/api/poses").json():
        client.delete(f"/api/poses/{p['id']}")
    ids = []
    for i, name in enumerate(["one", "two", "three"]):
        r = client.post("/api/poses", json={"name": name, "x": float(i), "y": 2.0 * i, "theta": 0.1 * i})
        assert r.status_code == 201, r.text
        ids.append(r.json()["id"])
    r = client.post(f"/api/poses/{ids[2]}/move", json={"direction": "up"})
    assert [p["name"] for p in r.json()] == ["one", "three", "two"]
    r = client.patch(f"/api/poses/{ids[0]}", json={"name": "first", "theta": 4.0})
    assert r.status_code == 200 and r.json()["theta"] == pytest.approx(4.0 - 2 * math.pi)
    assert client.patch("/api/poses/999999", json={"name": "x"}).status_code == 404
    assert client.post("/api/poses/999999/move", json={"direction": "up"}).status_code == 404
    assert client.post("/api/poses/999999/send").status_code == 404
    doc = client.get("/api/poses/export").json()
    assert [p["name"] for p in doc["poses"]] == ["first", "three", "two"]
    assert client.delete(f"/api/poses/{ids[1]}").status_code == 200
    assert [p["name"] for p in client.get("/api/poses").json()] == ["first", "three"]
    r = client.post("/api/poses/import", json={**doc, "replace": True})
    assert r.status_code == 200 and [p["name"] for p in r.json()] == ["first", "three", "two"]
    r = client.post("/api/poses/import", json={"poses": [{"name": "ok", "x": 0, "y": 0},
                                                          {"name": "", "x": 0, "y": 0}]})
    assert r.status_code == 422
    assert len(client.get("/api/poses").json()) == 3


def test_configured_password_hash_and_bad_hash(tmp_path):
    good = auth.hash_password("configured secret")
    stack = hmi_stack(tmp_path / "good", sets=[f'hmi_api.password_hash="{good}"'])
    (tmp_path / "good").mkdir()
    try:
        stack.start()
        wait_http(stack)
        with HmiClient(base_url(stack)) as c:
            assert c.post("/api/login", json={"password": "wrong"}).status_code == 401
            c.login("configured secret")
            assert c.get("/api/status").status_code == 200
        assert not first_run_passwords(stack)
        assert not (tmp_path / "good" / auth.FIRST_RUN_FILE).exists()
    finally:
        stack.stop()
    result = subprocess.run([sys.executable, "-m", "services.hmi_api", "--check-config",
                             "--set", 'hmi_api.password_hash="plaintext"'], capture_output=True, text=True,
                            timeout=60)
    assert result.returncode == 2 and "password_hash must look like scrypt" in result.stderr
