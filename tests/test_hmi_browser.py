"""Browser tests: Debian's chromium driven by Playwright through the web HMI, at a tablet size (1024x768).

``test_hmi_pages_against_hmi_api`` runs hmi_api alone; the test publishes a robot's messages (map, odometry,
pose, scan, wheels, nav status, paths, particles) on the stack's Zenoh router and checks what the pages show and
what the HMI sends back (cmd_vel while a jog button is held). ``test_hmi_drives_the_simulated_robot`` runs the
whole simulated stack: log in, enable, jog, teach a pose, reorder, send it and watch the robot arrive.
A screenshot of each page is kept under ``artifacts/hmi/`` (git-ignored; ``ZAGV_ARTIFACTS`` moves it).
Without chromium the tests skip, except with CI=true, where that is a failure.
"""

from __future__ import annotations

import math
import os
import shutil
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from proto import codec
from proto.messages import (
    LaserScan,
    ModuleState,
    NavStatus,
    OccupancyGrid,
    Odometry,
    Pose2D,
    PoseArray,
    PoseWithCovariance,
    Twist2D,
    WheelStates,
)
from proto.messages import Path as PathMsg
from tests.support.browser import wait_js
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

pytestmark = [pytest.mark.integration, pytest.mark.browser]

CHROMIUM = os.environ.get("ZAGV_CHROMIUM", "/usr/bin/chromium")
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync"]
ARTIFACTS = Path(os.environ.get("ZAGV_ARTIFACTS", Path(__file__).resolve().parents[1] / "artifacts")) / "hmi"
VIEWPORT = {"width": 1024, "height": 768}


@pytest.fixture(scope="module")
def browser():
    if not (Path(CHROMIUM).exists() or shutil.which(CHROMIUM)):
        message = f"chromium not found at {CHROMIUM} (apt-get install chromium, or set ZAGV_CHROMIUM)"
        if os.environ.get("CI") == "true":
            pytest.fail(message + "; CI=true requires the browser tests to run")
        pytest.skip(message)
    from playwright import sync_api  # the dev extra

    with sync_api.sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS, headless=True)
        yield b
        b.close()


def shot(page, name: str) -> Path:
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    path = ARTIFACTS / f"{name}.png"
    page.screenshot(path=str(path))
    return path


def watch_errors(page) -> list[str]:
    """Collect uncaught JavaScript errors and console errors of ``page``."""
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(f"pageerror: {exc}"))
    page.on("console", lambda msg: errors.append(f"console: {msg.text}") if msg.type == "error"
            and "status of 4" not in msg.text and "status of 503" not in msg.text else None)
    return errors


def login(page, url: str, password: str) -> None:
    page.goto(url + "/#control")
    page.fill("#login-password", "wrong")
    page.click("#login-btn")
    page.wait_for_selector("#login-error:has-text('wrong password')")
    page.fill("#login-password", password)
    page.click("#login-btn")
    page.wait_for_selector("#login", state="hidden")
    page.wait_for_selector("#chip-link:has-text('live')")


def toast_text(page) -> str:
    return page.inner_text("#toast")


# ---------------------------------------------------------------------------------------------- fake world


class RobotMessages:
    """Publishes what a robot's services would (20 Hz), so the pages have something real to show."""

    def __init__(self, session, keys) -> None:
        self.session = session
        self.keys = keys
        self.stop = threading.Event()
        self.pose = (1.5, 0.8, 0.4)
        grid = np.zeros((120, 200), dtype=np.int8)  # 10 m x 6 m room, 0.05 m cells, walls around
        grid[:3, :] = grid[-3:, :] = 100
        grid[:, :3] = grid[:, -3:] = 100
        grid[50:70, 120:126] = 100  # a pillar
        grid[100:117, 170:197] = -1  # an unexplored corner
        self.grid = OccupancyGrid(width=200, height=120, resolution=0.05, origin=Pose2D(x=-1.0, y=-1.0),
                                  data=grid.tobytes())
        self.thread = threading.Thread(target=self.run, daemon=True)

    def put(self, name, msg) -> None:
        self.session.put(self.keys(name), codec.encode(msg))

    def run(self) -> None:
        self.put("map", self.grid)
        rng = np.random.default_rng(1)
        x, y, th = self.pose
        angles = np.linspace(-2.35, 2.35, 541)
        path = np.array([[x + 0.1 * i, y + 0.05 * i, 0.3] for i in range(50)], dtype="<f4")
        parts = np.column_stack([x + rng.normal(0, 0.08, 300), y + rng.normal(0, 0.08, 300),
                                 th + rng.normal(0, 0.1, 300)]).astype("<f4")
        i = 0
        while not self.stop.is_set():
            t = i * 0.05
            self.put("odom", Odometry(stamp=t, pose=Pose2D(x=x, y=y, theta=th),
                                      twist=Twist2D(vx=0.1 * math.sin(t), vy=0.0, wz=0.2 * math.cos(t / 2))))
            self.put("pose", PoseWithCovariance(stamp=t, pose=Pose2D(x=x, y=y, theta=th),
                                                covariance=[0.004, 0, 0, 0, 0.004, 0, 0, 0, 0.002]))
            self.put("cmd_vel", Twist2D(vx=0.1 * math.sin(t - 0.3), wz=0.2 * math.cos((t - 0.3) / 2)))
            self.put("wheels", WheelStates(stamp=t, enabled=True, link_ok=True, loop_hz=100.0, modules=[
                ModuleState(steer_rad=0.3, speed_mps=0.12), ModuleState(steer_rad=-0.2, speed_mps=0.1)]))
            self.put("nav/status", NavStatus(stamp=t, state="driving", goal_id="g1", goal=Pose2D(x=6.0, y=3.2),
                                             distance_left_m=4.9))
            ranges = (2.5 + 0.8 * np.cos(3 * angles)).astype("<f4")
            self.put("scan", LaserScan(stamp=t, angle_min=-2.35, angle_max=2.35, angle_increment=4.7 / 540,
                                       range_min=0.05, range_max=20.0, ranges=ranges.tobytes(),
                                       mount=Pose2D(x=0.45)))
            if i % 10 == 0:
                self.put("nav/path", PathMsg(stamp=t, poses=path.tobytes()))
                self.put("nav/local_plan", PathMsg(stamp=t, poses=path[:12].tobytes()))
                self.put("particles", PoseArray(stamp=t, poses=parts.tobytes()))
            i += 1
            self.stop.wait(0.05)

    def __enter__(self) -> RobotMessages:
        self.thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop.set()
        self.thread.join(timeout=5)


# ---------------------------------------------------------------------------------------------- tests


def test_hmi_pages_against_hmi_api(browser, tmp_path):
    stack = hmi_stack(tmp_path, sets=["hmi_api.query_timeout_s=0.5"])
    try:
        stack.start()
        wait_http(stack)
        url = base_url(stack)
        session = stack.session()
        jogs: list[Twist2D] = []

        def on_cmd(sample) -> None:
            twist = codec.decode("cmd_vel", sample.payload.to_bytes())
            if twist.stamp > 1e6:  # hmi_api stamps with its wall clock; the fake robot's commands start at 0 s
                jogs.append(twist)

        sub = session.declare_subscriber(stack.keys("cmd_vel"), on_cmd)
        with RobotMessages(session, stack.keys):
            page = browser.new_page(viewport=VIEWPORT, accept_downloads=True)
            errors = watch_errors(page)
            page.goto(url + "/")
            page.wait_for_selector("#login-password")
            shot(page, "00-login")
            login(page, url, password_of(stack))
            wait_js(page, "window.zagv.state.map !== null", timeout_s=30)
            page.wait_for_selector("#st-odom:has-text('x 1.50')")
            assert "M1 17.2°" in page.inner_text("#st-modules")
            assert "driving" in page.inner_text("#chip-nav")

            # enable: hmi_api alone has no drive to answer, and the page says so
            page.click("#btn-enable")
            page.wait_for_selector("#toast:has-text('enable failed')")
            assert "drive/enable" in toast_text(page)
            shot(page, "01-control")

            # jog: hold "forward" in translate mode at 50 %: cmd_vel carries vx = 0.5 * 0.2 m/s while held
            page.click("#btn-mode")
            assert page.inner_text("#btn-mode") == "Mode: translate"
            robot_jogs = len(jogs)
            page.hover("#jog-forward")
            page.mouse.down()
            wait_for_sync(lambda: sum(1 for t in jogs[robot_jogs:] if t.vx == pytest.approx(0.1)) >= 5,
                          timeout_s=10, message="holding the jog button did not keep cmd_vel coming")
            page.mouse.up()
            held = [t for t in jogs[robot_jogs:] if t.vx == pytest.approx(0.1)]
            assert all(t.vy == 0.0 and t.wz == 0.0 for t in held)

            # pose database: teach the current pose, add one by hand, reorder, send
            page.click("button[data-tab=poses]")
            page.fill("#pose-name", "taught")
            page.click("#btn-teach")
            page.wait_for_selector("#pose-table tbody tr:has-text('taught')")
            page.fill("#pose-name", "dock")
            page.fill("#pose-x", "4.25")
            page.fill("#pose-y", "2")
            page.fill("#pose-theta", "1.57")
            page.click("#btn-add-pose")
            page.wait_for_selector("#pose-table tbody tr:has-text('dock')")
            names = page.eval_on_selector_all("#pose-table tbody td.name", "els => els.map(e => e.textContent)")
            assert names == ["taught", "dock"]
            page.click("#pose-table tbody tr:nth-child(2) button[data-act=up]")
            page.wait_for_selector("#pose-table tbody tr:nth-child(1):has-text('dock')")
            with HmiClient(url) as api:
                api.login(password_of(stack))
                stored = api.get("/api/poses").json()
            assert [p["name"] for p in stored] == ["dock", "taught"]
            assert (stored[1]["x"], stored[1]["y"]) == pytest.approx((1.5, 0.8))
            page.click("#pose-table tbody tr:nth-child(1) button[data-act=send]")
            page.wait_for_selector("#toast:has-text('send pose')")
            assert "nav/goal" in toast_text(page)
            page.click("#pose-table tbody tr:nth-child(2) button[data-act=edit]")
            page.fill("#pose-table tbody tr:nth-child(2) [data-k=name]", "taught (edited)")
            page.click("#pose-table tbody tr:nth-child(2) button[data-act=save]")
            page.wait_for_selector("#pose-table tbody tr:has-text('taught (edited)')")
            shot(page, "03-poses")

            # map: drag from a point to set a goal; without nav the page reports the refusal
            page.click("button[data-tab=map]")
            page.click("button[data-tool=goal]")
            box = page.locator("#map-big").bounding_box()
            cx, cy = box["x"] + box["width"] * 0.6, box["y"] + box["height"] * 0.5
            page.mouse.move(cx, cy)
            page.mouse.down()
            page.mouse.move(cx + 60, cy - 60, steps=5)
            page.mouse.up()
            page.wait_for_selector("#toast:has-text('goal failed')")
            page.click("button[data-tool=pan]")
            shot(page, "02-map")

            # curves and the CSV of recorded velocities
            page.click("button[data-tab=curves]")
            wait_js(page, "window.zagv.curves.rows.length > 20", timeout_s=30)
            with page.expect_download() as download:
                page.click("#btn-csv")
            csv_path = tmp_path / "velocities.csv"
            download.value.save_as(csv_path)
            lines = csv_path.read_text().splitlines()
            assert lines[0].startswith("t_s,cmd_vx_mps") and len(lines) > 20
            shot(page, "04-curves")
            page.set_viewport_size({"width": 768, "height": 1024})  # the tablet turned upright
            page.click("button[data-tab=control]")
            page.wait_for_timeout(300)
            shot(page, "05-control-portrait")
            assert not errors, errors
            page.close()
        sub.undeclare()
    finally:
        stack.stop()


@pytest.mark.slow
@pytest.mark.skipif(not full_stack_available(),
                    reason=f"needs the simulated stack; missing services: {', '.join(missing_services())}")
def test_hmi_drives_the_simulated_robot(browser, tmp_path):
    stack = hmi_stack(tmp_path, full=True)
    try:
        stack.start(ready_timeout_s=120)
        wait_http(stack)
        url = base_url(stack)
        page = browser.new_page(viewport=VIEWPORT)
        errors = watch_errors(page)
        login(page, url, password_of(stack))
        wait_js(page, "window.zagv.state.status && window.zagv.state.status.pose !== null"
                " && window.zagv.state.status.wheels && window.zagv.state.status.wheels.link_ok", timeout_s=60)
        page.click("#btn-enable")
        page.wait_for_selector("#chip-drive:has-text('drive enabled')", timeout=30_000)

        def odom_x() -> float:
            return page.evaluate("window.zagv.state.status.odom ? window.zagv.state.status.odom.x : 0")

        x0 = odom_x()
        page.hover("#jog-forward")
        page.mouse.down()
        wait_for_sync(lambda: odom_x() > x0 + 0.05, timeout_s=30, message="jog did not move the robot")
        page.mouse.up()
        shot(page, "sim-01-control")

        page.click("button[data-tab=poses]")
        page.fill("#pose-name", "start")
        page.click("#btn-teach")
        page.wait_for_selector("#pose-table tbody tr:has-text('start')")
        page.fill("#pose-name", "goal")
        page.fill("#pose-x", "2.5")
        page.fill("#pose-y", "0.3")
        page.fill("#pose-theta", "0")
        page.click("#btn-add-pose")
        page.wait_for_selector("#pose-table tbody tr:has-text('goal')")
        page.click("#pose-table tbody tr:nth-child(2) button[data-act=up]")
        page.wait_for_selector("#pose-table tbody tr:nth-child(1):has-text('goal')")
        page.click("#pose-table tbody tr:nth-child(1) button[data-act=send]")
        page.wait_for_selector("#toast:has-text('send pose')")
        assert "failed" not in toast_text(page), toast_text(page)

        def arrived() -> bool:
            s = page.evaluate("window.zagv.state.status")
            p, n = s["pose"], s["nav"]
            return bool(p and n and n["state"] == "succeeded" and math.hypot(p["x"] - 2.5, p["y"] - 0.3) < 0.1)

        started = time.monotonic()
        wait_for_sync(arrived, timeout_s=180, poll_s=0.2, message="the robot did not arrive at the sent pose")
        print(f"\nsent pose reached in {time.monotonic() - started:.1f} s (wall)")
        shot(page, "sim-03-poses")
        page.click("button[data-tab=map]")
        shot(page, "sim-02-map")
        page.click("button[data-tab=curves]")
        shot(page, "sim-04-curves")
        assert not errors, errors
        page.close()
    finally:
        stack.stop()
