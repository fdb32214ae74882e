"""The fleet service's HTTP API against stand-in robots: a real site router and a real fleet process; one Zenoh
session plays two robots (r1, r2) with their health tokens, messages and the queryables the site may use.

Shown: the robot HMI's login rules, every robot with pose, footprint, path, state, battery and faults, a goal and
a pose list reaching only the robot they were sent to, refusals and bad input named, and a robot that leaves the
site (its tokens go) and comes back.
"""

from __future__ import annotations

import json
import math
import sys
import threading
from collections.abc import Iterator

import httpx
import numpy as np
import pytest
import zenoh

from proto import codec
from proto.messages import (
    GoalReply,
    GoalRequest,
    ModuleState,
    NavStatus,
    OccupancyGrid,
    Odometry,
    Pose2D,
    PoseWithCovariance,
    Reply,
    Transform2D,
    WaypointsRequest,
    WheelStates,
)
from proto.messages import Path as PathMsg
from services.common.session import open_session
from services.common.settings import ZenohSettings
from tests.support.browser import ARTIFACTS as BROWSER_ARTIFACTS
from tests.support.browser import CHROMIUM, CHROMIUM_ARGS, click_robot, sync_playwright_or_skip, wait_js
from tests.support.hmi import HmiClient
from tests.support.site import Process, router_config
from tests.support.stack import free_port
from tests.support.waiting import wait_for_sync

pytestmark = pytest.mark.integration
ARTIFACTS = BROWSER_ARTIFACTS / "fleet"


class StandIns:
    """Robots r1 and r2 on one session: latched-style queryables, health tokens, and the requests they got."""

    def __init__(self, session: zenoh.Session) -> None:
        self.session = session
        self.requests: list[tuple[str, object]] = []
        self.lock = threading.Lock()
        self.refuse: set[str] = set()
        self.tokens: dict[str, list] = {}
        grid = OccupancyGrid(resolution=0.1, width=40, height=30, origin=Pose2D(x=-1.0, y=-1.0),
                             data=np.zeros(1200, dtype=np.int8).tobytes())
        self.latched = {"map": grid}
        self._declared = []
        for rid in ("r1", "r2"):
            self._declared.append(session.declare_queryable(f"agv/{rid}/map", self._latched_answer))
            self._declared.append(session.declare_queryable(f"agv/{rid}/nav/goal", self._goal))
            self._declared.append(session.declare_queryable(f"agv/{rid}/nav/waypoints", self._waypoints))
            self._declared.append(session.declare_queryable(f"agv/{rid}/nav/cancel", self._reply_ok))
            self._declared.append(session.declare_queryable(f"agv/{rid}/drive/estop", self._reply_ok))
            self.join(rid)

    def join(self, rid: str) -> None:
        self.tokens[rid] = [self.session.liveliness().declare_token(f"agv/{rid}/@health/{s}") for s in ("nav", "drive")]

    def leave(self, rid: str) -> None:
        for t in self.tokens.pop(rid):
            t.undeclare()

    def _latched_answer(self, q: zenoh.Query) -> None:
        q.reply(q.key_expr, codec.encode(self.latched["map"]))

    def _record(self, q: zenoh.Query, msg_type: type) -> tuple[str, object]:
        rid = str(q.key_expr).split("/")[1]
        msg = codec.decode_as(msg_type, q.payload.to_bytes(), str(q.key_expr))
        with self.lock:
            self.requests.append((str(q.key_expr), msg))
        return rid, msg

    def _goal(self, q: zenoh.Query) -> None:
        rid, msg = self._record(q, GoalRequest)
        ok = rid not in self.refuse
        q.reply(q.key_expr, codec.encode(GoalReply(accepted=ok, goal_id=msg.id, reason="" if ok else "no route")))

    def _waypoints(self, q: zenoh.Query) -> None:
        _, msg = self._record(q, WaypointsRequest)
        q.reply(q.key_expr, codec.encode(GoalReply(accepted=True, goal_id=msg.id)))

    def _reply_ok(self, q: zenoh.Query) -> None:
        rid = str(q.key_expr).split("/")[1]
        with self.lock:
            self.requests.append((str(q.key_expr), None))
        q.reply(q.key_expr, codec.encode(Reply(ok=True, message=f"{rid} ok")))

    def publish(self) -> None:
        """Each robot's state: r1 near the origin and healthy, r2 at (2, 1) with a path, a fault and low battery."""
        s = self.session
        for rid, (x, y), volts, fault in (("r1", (0.5, 0.2), 51.0, ""), ("r2", (2.0, 1.0), 45.0, "overcurrent")):
            s.put(f"agv/{rid}/odom", codec.encode(Odometry(pose=Pose2D(x=x, y=y, theta=0.3))))
            s.put(f"agv/{rid}/tf/map_odom", codec.encode(Transform2D(x=0.0, y=0.0, theta=0.0)))
            s.put(f"agv/{rid}/pose", codec.encode(PoseWithCovariance(pose=Pose2D(x=x, y=y, theta=0.3))))
            s.put(f"agv/{rid}/wheels", codec.encode(WheelStates(
                enabled=True, link_ok=True, fault=fault,
                modules=[ModuleState(battery_v=volts), ModuleState(battery_v=volts)])))
            s.put(f"agv/{rid}/nav/status", codec.encode(NavStatus(state="driving" if rid == "r2" else "idle")))
        path = np.array([[2.0, 1.0, 0.0], [2.5, 1.5, 0.0], [3.0, 2.0, 0.0]], dtype="<f4").tobytes()
        s.put("agv/r2/nav/path", codec.encode(PathMsg(poses=path)))

    def received(self, key: str) -> list[object]:
        with self.lock:
            return [m for k, m in self.requests if k == key]


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[HmiClient, str, StandIns]]:
    root = tmp_path_factory.mktemp("fleet")
    site_endpoint = f"tcp/127.0.0.1:{free_port()}"
    (root / "site.json5").write_text(json.dumps(router_config(site_endpoint, [], gossip=False)))
    router = Process([sys.executable, "-m", "services.cli", "router", "--config", str(root / "site.json5")],
                     root / "router.log")
    port = free_port()
    service = Process([sys.executable, "-m", "services.fleet", "--robot-id", "site", "--connect", site_endpoint,
                       "--set", f"fleet.port={port}", "--set", f'fleet.state_dir="{root / "state"}"',
                       "--set", "fleet.login_lockout_initial_s=30.0"], root / "fleet.log")
    session = None
    try:
        router.wait_line("listening on", timeout_s=60)
        session = open_session(ZenohSettings(mode="client", connect=[site_endpoint]))
        robots = StandIns(session)
        password = service.wait_line(r"first-run password: (\S+)", timeout_s=60).group(1)
        base = f"http://127.0.0.1:{port}"

        def answers() -> bool:
            assert service.proc.poll() is None, service.output()
            try:
                return httpx.get(base + "/", timeout=2.0).status_code == 200
            except httpx.TransportError:
                return False

        wait_for_sync(answers, timeout_s=60, poll_s=0.1, message="the fleet view never answered")
        yield HmiClient(base), password, robots
    finally:
        if session is not None:
            session.close()
        service.stop()
        router.stop()


def fleet_doc(client: HmiClient) -> dict:
    r = client.get("/api/fleet")
    assert r.status_code == 200, r.text
    return {robot["id"]: robot for robot in r.json()["robots"]}


def test_login_rules_are_the_robot_hmis(fleet) -> None:
    client, password, _ = fleet
    anonymous = httpx.Client(base_url=str(client.base_url), timeout=10.0)
    assert anonymous.get("/api/fleet").status_code == 401
    assert anonymous.post("/api/robots/r1/goal", json={"x": 0, "y": 0}).status_code == 401
    assert anonymous.post("/api/login", json={"password": "wrong"}).status_code == 401
    assert anonymous.post("/api/login", content=b"password=x",
                          headers={"content-type": "application/x-www-form-urlencoded"}).status_code == 415
    r = anonymous.get("/", headers={"host": "evil.example"})
    assert r.status_code == 400, "a foreign Host header must be refused (DNS rebinding)"
    assert anonymous.get("/").headers["x-frame-options"] == "DENY"
    client.login(password)
    assert client.get("/api/fleet").status_code == 200


def test_every_robot_with_pose_footprint_path_state_battery_and_faults(fleet) -> None:
    client, password, robots = fleet
    if not client.token:
        client.login(password)

    def both_seen() -> bool:
        robots.publish()
        doc = fleet_doc(client)
        return {"r1", "r2"} <= doc.keys() and all(doc[r]["pose"] and doc[r]["battery"] and doc[r]["nav"]
                                                   for r in ("r1", "r2")) and bool(doc["r2"]["path"])

    wait_for_sync(both_seen, timeout_s=30, poll_s=0.1, message="the fleet view never showed both robots")
    doc = fleet_doc(client)
    assert "site" not in doc, "the fleet service's own id is not a robot"
    r1, r2 = doc["r1"], doc["r2"]
    assert r1["present"] and r2["present"]
    assert r2["pose"] == {"x": 2.0, "y": 1.0, "theta": 0.3, "frame": "map"}
    assert r1["footprint"]["radius_m"] == pytest.approx(0.63)
    assert r2["path"] == [2.0, 1.0, 2.5, 1.5, 3.0, 2.0]
    assert r2["nav"]["state"] == "driving" and r1["nav"]["state"] == "idle"
    assert r1["battery"] == {"voltage_v": 51.0, "percent": 87.5}
    assert r2["battery"]["percent"] == 12.5
    assert r1["faults"] == [] and r2["faults"] == ["drive: overcurrent"]
    m = client.get("/api/map").json()
    assert m["available"] and m["width"] == 40 and m["png_base64"], "the site map is the robots' map"


def test_a_goal_and_a_pose_list_reach_only_the_robot_they_were_sent_to(fleet) -> None:
    client, password, robots = fleet
    if not client.token:
        client.login(password)
    wait_for_sync(lambda: {"r1", "r2"} <= fleet_doc(client).keys(), timeout_s=30, poll_s=0.1)
    r = client.post("/api/robots/r2/goal", json={"x": 1.5, "y": -0.5, "theta": 1.0})
    assert r.status_code == 200, r.text
    goals = robots.received("agv/r2/nav/goal")
    assert len(goals) == 1 and goals[0].pose == Pose2D(x=1.5, y=-0.5, theta=1.0) and goals[0].id == r.json()["goal_id"]
    assert robots.received("agv/r1/nav/goal") == []
    poses = [{"x": 1.0, "y": 0.0, "theta": 0.0}, {"x": 2.0, "y": 0.5, "theta": 0.5}, {"x": 3.0, "y": 1.0}]
    r = client.post("/api/robots/r1/poses", json={"poses": poses})
    assert r.status_code == 200, r.text
    (sequence,) = robots.received("agv/r1/nav/waypoints")
    assert [(w.pose.x, w.pose.y, w.pose.theta) for w in sequence.waypoints] == [(1.0, 0.0, 0.0), (2.0, 0.5, 0.5),
                                                                               (3.0, 1.0, 0.0)]
    assert robots.received("agv/r2/nav/waypoints") == []
    assert client.post("/api/robots/r1/cancel").status_code == 200
    assert client.post("/api/robots/r2/estop").status_code == 200
    assert len(robots.received("agv/r1/nav/cancel")) == 1 and len(robots.received("agv/r2/drive/estop")) == 1
    assert robots.received("agv/r2/nav/cancel") == [] and robots.received("agv/r1/drive/estop") == []


@pytest.mark.parametrize(("path", "body", "status", "words"), [
    ("/api/robots/r9/goal", {"x": 1.0, "y": 1.0}, 404, "no robot 'r9'"),
    ("/api/robots/r1/goal", {"x": math.nan, "y": 1.0}, 422, ""),
    ("/api/robots/r1/goal", {"x": 1e9, "y": 1.0}, 422, "x"),
    ("/api/robots/r1/goal", {"x": "1", "y": 1.0}, 422, "x"),
    ("/api/robots/r1/poses", {"poses": []}, 422, "poses"),
    ("/api/robots/r1/poses", {"poses": [{"x": 0.0, "y": 0.0}] * 201}, 422, "fleet.max_poses"),
    ("/api/robots/r1%2Fx/goal", {"x": 1.0, "y": 1.0}, 404, ""),
])
def test_bad_requests_are_named(fleet, path: str, body: dict, status: int, words: str) -> None:
    client, password, _ = fleet
    if not client.token:
        client.login(password)
    content = json.dumps(body, allow_nan=True).encode()
    r = client.post(path, content=content, headers={"content-type": "application/json"})
    assert r.status_code == status, r.text
    assert words in r.text


def test_a_refusal_is_409_with_the_robots_reason(fleet) -> None:
    client, password, robots = fleet
    if not client.token:
        client.login(password)
    robots.refuse.add("r1")
    try:
        r = client.post("/api/robots/r1/goal", json={"x": 9.0, "y": 9.0})
        assert r.status_code == 409 and "no route" in r.json()["detail"]
    finally:
        robots.refuse.discard("r1")


@pytest.mark.browser
def test_the_page_draws_every_robot_and_sends_goals_to_the_one_picked(fleet) -> None:
    """Debian chromium: log in, both robots drawn on the map, r2 picked by a click on its footprint; a goal from the
    form and a pose list from two map clicks reach r2 only."""
    sync_api = sync_playwright_or_skip()
    client, password, robots = fleet
    if not client.token:
        client.login(password)

    def both_drawable() -> bool:
        robots.publish()
        doc = fleet_doc(client)
        return all(doc.get(r, {}).get("present") and doc[r]["pose"] for r in ("r1", "r2"))

    wait_for_sync(both_drawable, timeout_s=30, poll_s=0.1, message="the robots never showed up")
    goals_before = {r: len(robots.received(f"agv/{r}/nav/goal")) for r in ("r1", "r2")}
    lists_before = {r: len(robots.received(f"agv/{r}/nav/waypoints")) for r in ("r1", "r2")}
    with sync_api.sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS, headless=True)
        try:
            page = browser.new_page(viewport={"width": 1024, "height": 768})
            errors: list[str] = []
            page.on("pageerror", lambda exc: errors.append(str(exc)))
            page.goto(str(client.base_url) + "/")
            page.fill("#login-password", password)
            page.click("#login-btn")
            wait_js(page, "document.querySelector('#map').dataset.drawn === 'r1,r2'", 30)
            wait_js(page, "window.fleetView.state.map !== null", 30)
            assert "battery ?" not in page.inner_text("li[data-robot=r2] .meta")
            assert "drive: overcurrent" in page.inner_text("li[data-robot=r2] .faults")
            click_robot(page, "r2")
            wait_js(page, "document.querySelector('#selected').textContent === 'r2'", 10)
            page.fill("#goal-x", "1.25")
            page.fill("#goal-y", "0.5")
            page.fill("#goal-theta", "90")
            page.click("#btn-goal")
            wait_js(page, "document.querySelector('#message').textContent.includes('accepted')", 20)
            # a pose list: two clicks on free map cells in pose-list mode, then send
            page.check("#pose-mode")
            box = page.locator("#map").bounding_box()
            for wx, wy in ((0.5, 1.5), (1.0, 1.8)):  # clear of both footprints (a click on one picks it)
                x, y = page.evaluate(f"() => window.fleetView.worldToCanvas({wx}, {wy})")
                page.mouse.click(box["x"] + x, box["y"] + y)
            wait_js(page, "document.querySelector('#pose-count').textContent === '2'", 10)
            page.click("#btn-send-poses")
            wait_js(page, "document.querySelector('#message').textContent.includes('pose list')", 20)
            ARTIFACTS.mkdir(parents=True, exist_ok=True)
            page.screenshot(path=str(ARTIFACTS / "fleet-stand-ins.png"))
            assert not errors, f"JavaScript errors: {errors}"
        finally:
            browser.close()
    goals = robots.received("agv/r2/nav/goal")[goals_before["r2"]:]
    assert len(goals) == 1 and goals[0].pose.x == pytest.approx(1.25) and goals[0].pose.y == pytest.approx(0.5)
    assert goals[0].pose.theta == pytest.approx(math.pi / 2, abs=1e-6)
    (sequence,) = robots.received("agv/r2/nav/waypoints")[lists_before["r2"]:]
    assert [(round(w.pose.x, 1), round(w.pose.y, 1)) for w in sequence.waypoints] == [(0.5, 1.5), (1.0, 1.8)]
    assert len(robots.received("agv/r1/nav/goal")) == goals_before["r1"], "r1 was not picked"
    assert len(robots.received("agv/r1/nav/waypoints")) == lists_before["r1"], "r1 was not picked"


def test_a_robot_that_leaves_is_shown_away_and_back(fleet) -> None:
    client, password, robots = fleet
    if not client.token:
        client.login(password)
    wait_for_sync(lambda: fleet_doc(client).get("r2", {}).get("present"), timeout_s=30, poll_s=0.1)
    robots.leave("r2")
    wait_for_sync(lambda: not fleet_doc(client)["r2"]["present"], timeout_s=20, poll_s=0.05,
                  message="the fleet view did not see r2 leave")
    r2 = fleet_doc(client)["r2"]
    assert r2["faults"][0].startswith("offline") and r2["pose"] is not None, "the last pose stays, marked away"
    r = client.post("/api/robots/r2/goal", json={"x": 1.0, "y": 1.0})
    assert r.status_code == 503 and "left" in r.json()["detail"]
    assert fleet_doc(client)["r1"]["present"], "the other robot stays"
    robots.join("r2")
    wait_for_sync(lambda: fleet_doc(client)["r2"]["present"], timeout_s=20, poll_s=0.05,
                  message="the fleet view did not see r2 come back")
    events = client.get("/api/fleet").json()["events"]
    assert [e["event"] for e in events if e["robot_id"] == "r2"][-2:] == ["left", "joined"]
