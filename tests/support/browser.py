"""Debian's chromium through Playwright (executable_path), for the browser tests of the web HMIs."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

from tests.support.waiting import wait_for_sync

CHROMIUM = os.environ.get("ZAGV_CHROMIUM", "/usr/bin/chromium")
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync"]
ARTIFACTS = Path(os.environ.get("ZAGV_ARTIFACTS", Path(__file__).resolve().parents[2] / "artifacts"))


def sync_playwright_or_skip():
    """playwright's sync API, or a skip naming what is missing (a failure for chromium under CI=true)."""
    if not (Path(CHROMIUM).exists() or shutil.which(CHROMIUM)):
        message = f"chromium not found at {CHROMIUM} (apt-get install chromium, or set ZAGV_CHROMIUM)"
        if os.environ.get("CI") == "true":
            pytest.fail(message + "; CI=true requires the browser tests to run")
        pytest.skip(message)
    return pytest.importorskip("playwright.sync_api", reason="playwright is in the dev extra")


def wait_js(page, expression: str, timeout_s: float) -> None:
    """Poll a JavaScript expression through the DevTools protocol (page.evaluate) until it is true: the pages' CSP
    forbids eval, which Playwright's own wait_for_function predicates need."""
    wait_for_sync(lambda: page.evaluate(f"() => Boolean({expression})"), timeout_s=timeout_s, poll_s=0.1,
                  message=f"never true in the page: {expression}")


def click_robot(page, robot_id: str) -> None:
    """Click the fleet view's map on ``robot_id``'s drawn footprint."""
    x, y = page.evaluate("(id) => { const p = window.fleetView.state.fleet.robots.find(r => r.id === id).pose;"
                         " return window.fleetView.worldToCanvas(p.x, p.y); }", robot_id)
    box = page.locator("#map").bounding_box()
    page.mouse.click(box["x"] + x, box["y"] + y)
