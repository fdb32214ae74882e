"""The fleet view on a site of simulated robots (tests/support/site.py): one router per robot linked to a site
router, each robot its own simulated stack, the fleet service on the site router.

Both are ``long`` (whole robot stacks; `make test-long`); tests/test_fleet_api.py keeps the fleet view's API and
page in ``make test`` against stand-in robots.

- ``test_fleet_view_draws_every_robot_and_a_goal_moves_only_that_robot`` (browser, 2 robots): Debian chromium
  through Playwright logs in, sees every robot drawn on the shared map, picks one robot and sends it a goal; that
  robot arrives (ground truth) and the other does not move.
- ``test_robots_finish_their_goals_without_the_site_router`` (long, 3 robots): goals through the fleet API, the site
  router killed while every robot drives; each robot still reaches its goal, the site sees the robots leave and,
  once the router is back, has every robot present again within 2 s (measured from the router's "listening" line).
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from proto import codec
from proto.messages import NavStatus
from tests.support.browser import ARTIFACTS as BROWSER_ARTIFACTS
from tests.support.browser import CHROMIUM, CHROMIUM_ARGS, click_robot, sync_playwright_or_skip, wait_js
from tests.support.hmi import HmiClient, full_stack_available, missing_services
from tests.support.site import RobotPlan, Site
from tests.support.waiting import wait_for_sync

pytestmark = pytest.mark.integration

ARTIFACTS = BROWSER_ARTIFACTS / "fleet"
#: start poses in the corridor world: the lobby, and two places along the main corridor
STARTS = {"r1": (0.0, 0.0, 0.0), "r2": (8.0, 3.2, 0.0), "r3": (16.0, 3.2, 0.0)}
#: a goal per robot, 1.5-3 m ahead along free space
GOALS = {"r1": (3.0, 0.1, 0.0), "r2": (10.5, 3.2, 0.0), "r3": (18.0, 3.4, 0.0)}
#: ground-truth distance (m) within which a goal counts as reached here (nav's own tolerance is 0.05 m)
REACHED_M = 0.1
#: how far (m) a robot that was sent nothing may drift (it must not move at all)
STILL_M = 0.02


@pytest.fixture
def site_factory(tmp_path: Path) -> Iterator:
    if not full_stack_available():
        pytest.skip(f"robot services missing: {missing_services()}")
    sites: list[Site] = []

    def make(robot_ids: list[str]) -> Site:
        site = Site(tmp_path / f"site{len(sites)}", [RobotPlan(r, STARTS[r]) for r in robot_ids])
        sites.append(site)
        return site.start()

    yield make
    for site in sites:
        site.stop()


def fleet_client(site: Site) -> HmiClient:
    client = HmiClient(site.fleet_url)
    wait_for_sync(lambda: _answers(site), timeout_s=60, poll_s=0.1, message="the fleet view never answered HTTP:\n"
                  + (site.fleet.output() if site.fleet else ""))
    client.login(site.fleet_password())
    return client


def _answers(site: Site) -> bool:
    assert site.fleet and site.fleet.proc.poll() is None, f"the fleet service exited:\n{site.fleet.output()}"
    try:
        return httpx.get(site.fleet_url + "/", timeout=2.0).status_code == 200
    except httpx.TransportError:
        return False


def robots_by_id(client: HmiClient) -> dict[str, dict]:
    r = client.get("/api/fleet")
    assert r.status_code == 200, r.text
    return {robot["id"]: robot for robot in r.json()["robots"]}


def all_tracking(client: HmiClient, ids: list[str]) -> bool:
    robots = robots_by_id(client)
    return all(rid in robots and robots[rid]["present"] and robots[rid]["localization"] == "tracking"
               and robots[rid]["pose"] is not None for rid in ids)


def distance(a: tuple[float, ...] | None, b: tuple[float, ...]) -> float:
    return math.hypot(a[0] - b[0], a[1] - b[1]) if a is not None else math.inf


@pytest.mark.browser
@pytest.mark.long
@pytest.mark.timeout(1200)  # two full simulated robots: minutes on a loaded machine
def test_fleet_view_draws_every_robot_and_a_goal_moves_only_that_robot(site_factory) -> None:
    sync_api = sync_playwright_or_skip()
    ids = ["r1", "r2"]
    site = site_factory(ids)
    client = fleet_client(site)
    wait_for_sync(lambda: all_tracking(client, ids), timeout_s=90, poll_s=0.2,
                  message=f"the robots never showed up tracking at the site: {robots_by_id(client)}")
    starts = {rid: site.true_pose(rid) for rid in ids}
    assert all(starts.values()), f"no ground truth from a robot: {starts}"
    with sync_api.sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS, headless=True)
        try:
            page = browser.new_page(viewport={"width": 1280, "height": 800})
            errors: list[str] = []
            page.on("pageerror", lambda exc: errors.append(str(exc)))
            page.goto(site.fleet_url + "/")
            page.fill("#login-password", site.fleet_password())
            page.click("#login-btn")
            # every robot drawn on the map (the canvas lists what it drew) and listed as at the site
            wait_js(page, "document.querySelector('#map').dataset.drawn === 'r1,r2'", 30)
            wait_js(page, "window.fleetView.state.map !== null", 30)
            for rid in ids:
                assert "at the site" in page.inner_text(f"li[data-robot={rid}] .meta")
            ARTIFACTS.mkdir(parents=True, exist_ok=True)
            page.screenshot(path=str(ARTIFACTS / "fleet-two-robots.png"))
            # pick r2 on the map itself: a click on its footprint selects it
            click_robot(page, "r2")
            wait_js(page, "document.querySelector('#selected').textContent === 'r2'", 10)
            gx, gy, gth = GOALS["r2"]
            page.fill("#goal-x", str(gx))
            page.fill("#goal-y", str(gy))
            page.fill("#goal-theta", str(math.degrees(gth)))
            page.click("#btn-goal")
            wait_js(page, "document.querySelector('#message').textContent.includes('accepted')", 20)
            wait_for_sync(lambda: distance(site.true_pose("r2"), GOALS["r2"]) < REACHED_M, timeout_s=120, poll_s=0.1,
                          message=f"r2 never reached its goal: at {site.true_pose('r2')}")
            wait_js(page, "document.querySelector('li[data-robot=r2] .meta').dataset.nav === 'succeeded'", 30)
            page.screenshot(path=str(ARTIFACTS / "fleet-r2-arrived.png"))
            assert not errors, f"JavaScript errors: {errors}"
        finally:
            browser.close()
    moved_r1 = distance(site.true_pose("r1"), starts["r1"])
    assert moved_r1 < STILL_M, f"r1 was sent nothing but moved {moved_r1:.3f} m"
    assert robots_by_id(client)["r1"]["nav"]["state"] in ("idle", None) or \
        robots_by_id(client)["r1"]["nav"]["goal_id"] == "", "r1 got a goal"
    assert not site.collided(), f"contact with a wall: {site.collided()}"


@pytest.mark.long
@pytest.mark.timeout(1800)  # three full simulated robots
def test_robots_finish_their_goals_without_the_site_router(site_factory) -> None:
    ids = ["r1", "r2", "r3"]
    site = site_factory(ids)
    client = fleet_client(site)
    wait_for_sync(lambda: all_tracking(client, ids), timeout_s=180, poll_s=0.2,
                  message=f"the robots never showed up tracking at the site: {robots_by_id(client)}")
    nav: dict[str, NavStatus] = {}
    lock = threading.Lock()
    for rid in ids:  # watched on each robot's own router: it must not depend on the site router
        def on_status(sample, rid=rid) -> None:
            with lock:
                nav[rid] = codec.decode_as(NavStatus, sample.payload.to_bytes(), str(sample.key_expr))
        site.robot_session(rid).declare_subscriber(f"agv/{rid}/nav/status", on_status)
    goal_ids = {}
    for rid in ids:
        x, y, th = GOALS[rid]
        r = client.post(f"/api/robots/{rid}/goal", json={"x": x, "y": y, "theta": th})
        assert r.status_code == 200, r.text
        goal_ids[rid] = r.json()["goal_id"]

    def driving(rid: str) -> bool:
        with lock:
            s = nav.get(rid)
        return s is not None and s.goal_id == goal_ids[rid] and s.state in ("driving", "rotating")

    wait_for_sync(lambda: all(driving(rid) for rid in ids), timeout_s=60, poll_s=0.05,
                  message=f"not every robot started driving: {nav}")
    assert site.site_router
    site.site_router.kill()
    killed_at = time.monotonic()
    # the site sees every robot leave
    wait_for_sync(lambda: not _answers(site) or not any(r["present"] for r in robots_by_id(client).values()),
                  timeout_s=20, poll_s=0.1, message="the site still shows robots present without its router")

    def finished(rid: str) -> bool:
        with lock:
            s = nav.get(rid)
        return s is not None and s.goal_id == goal_ids[rid] and s.state == "succeeded"

    down_s = 5.0
    wait_for_sync(lambda: time.monotonic() - killed_at >= down_s, timeout_s=down_s + 1, poll_s=0.05)
    still_driving = [rid for rid in ids if not finished(rid)]
    back_at = site.start_site_router()
    wait_for_sync(lambda: all(r["present"] for r in robots_by_id(client).values()) and
                  len(robots_by_id(client)) == len(ids), timeout_s=30, poll_s=0.02,
                  message=f"the site did not see every robot again: {robots_by_id(client)}")
    back_after_s = time.monotonic() - back_at
    wait_for_sync(lambda: all(finished(rid) for rid in ids), timeout_s=180, poll_s=0.1,
                  message=f"not every robot finished its goal: {nav}")
    errors = {rid: distance(site.true_pose(rid), GOALS[rid]) for rid in ids}
    robots = robots_by_id(client)
    print(f"site view back {back_after_s:.2f} s after the router returned; robots still driving when it returned: "
          f"{still_driving}; final ground-truth errors (m): "
          + ", ".join(f"{rid} {e:.3f}" for rid, e in errors.items())
          + "; leaves seen: " + ", ".join(f"{rid} {robots[rid]['leaves']}" for rid in ids))
    assert back_after_s <= 2.0, f"the site view came back {back_after_s:.2f} s after its router"
    assert all(e < REACHED_M for e in errors.values()), f"goals not reached: {errors}"
    assert all(robots[rid]["leaves"] >= 1 for rid in ids), "the site did not see every robot leave"
    assert not site.collided(), f"contact with a wall: {site.collided()}"
