"""Several robots in one simulated world, end to end: ``zagv up --robot ... --robot ...`` with each robot's own CAN
bus, emulated LMS111 and drive/lidar services; each robot's lidar sees the other's chassis, and driving one into
the other is a contact both report. The full multi-robot navigation scenarios (crossing routes, the depot map, a
passage too narrow for two) are the long suite at the end."""

from __future__ import annotations

import math
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from proto import codec
from proto.keys import Keys
from proto.messages import Clock, Empty, GroundTruth, LaserScan, Reply, Twist2D, WheelStates
from tests.support.waiting import wait_for_sync

RADIUS_M = 0.63
LASER_X_M = 0.45


class Robot:
    """Test-side view of one robot of the fleet: clock, ground truth, scans; streams cmd_vel."""

    def __init__(self, session, rid: str) -> None:
        self.session, self.keys = session, Keys(rid)
        self.lock = threading.Lock()
        self.sim_now = 0.0
        self.truth: GroundTruth | None = None
        self.scan: LaserScan | None = None
        self.wheels: WheelStates | None = None
        self._subs = [
            self._sub("wheels", WheelStates, lambda m: setattr(self, "wheels", m)),
            self._sub("clock", Clock, self._on_clock),
            self._sub("sim/ground_truth", GroundTruth, lambda m: setattr(self, "truth", m)),
            self._sub("scan", LaserScan, lambda m: setattr(self, "scan", m)),
        ]
        self.cmd = session.declare_publisher(self.keys("cmd_vel"))

    def _sub(self, name: str, t: type, cb):
        key = self.keys(name)
        return self.session.declare_subscriber(key, lambda s: cb(codec.decode_as(t, s.payload.to_bytes(), key)))

    def _on_clock(self, c: Clock) -> None:
        self.sim_now = max(self.sim_now, c.stamp)

    def query(self, name: str) -> Reply:
        deadline = time.monotonic() + 30.0
        while True:  # the queryable may not be matched yet: ask again until the deadline
            replies = list(self.session.get(self.keys(name), payload=codec.encode(Empty()), timeout=5.0))
            if replies and replies[0].ok is not None:
                return codec.decode_as(Reply, replies[0].ok.payload.to_bytes())
            assert time.monotonic() < deadline, f"{self.keys(name)} did not answer"
            time.sleep(0.2)

    def range_ahead_m(self, after_s: float) -> float:
        """The median range of the beams within ±1° of straight ahead, from a scan taken after ``after_s`` (sim)."""
        wait_for_sync(lambda: self.scan is not None and self.scan.stamp > after_s, timeout_s=60,
                      message=f"no scan of {self.keys.robot_id} after {after_s} s")
        scan = self.scan
        ranges = codec.array(scan, "ranges")
        angles = scan.angle_min + np.arange(len(ranges)) * scan.angle_increment
        return float(np.median(ranges[np.abs(angles) <= math.radians(1.0)]))


@pytest.mark.integration
@pytest.mark.slow
def test_two_robots_see_each_other_and_a_push_is_a_contact_both_report(stack_factory) -> None:
    # r1 and r2 face each other 2.4 m apart (centres) in the empty room: straight ahead, each laser (0.45 m ahead
    # of its robot's centre) sees the other chassis at 2.4 - 0.63 - 0.45 = 1.32 m; alone it would see a far wall
    stack = stack_factory(services=["sim", "drive", "lidar"], world="empty_room", speed=1.0, robot_id="r1",
                          extra_args=["--robot", "r1:-2.4,-2.0,0.0", "--robot", f"r2:0.0,-2.0,{math.pi!r}"],
                          fleet_size=2).start(ready_timeout_s=120.0)
    session = stack.session()
    r1, r2 = Robot(session, "r1"), Robot(session, "r2")
    wait_for_sync(lambda: r1.truth is not None and r2.truth is not None, timeout_s=30, message="no ground truth")
    expected = 2.4 - RADIUS_M - LASER_X_M
    assert r1.range_ahead_m(r1.sim_now) == pytest.approx(expected, abs=0.05)
    assert r2.range_ahead_m(r2.sim_now) == pytest.approx(expected, abs=0.05)
    # each robot is its own stack: r1's drive enables and moves r1 only (once its CAN link is up: the drive
    # retries the link while a loaded machine keeps the emulated controllers from answering in time)
    wait_for_sync(lambda: r1.wheels is not None and r1.wheels.link_ok, timeout_s=120,
                  message="r1's drive never reported a live CAN link")
    assert r1.query("drive/enable").ok
    deadline = time.monotonic() + 120.0
    while not r1.truth.collided:  # r1 drives at r2 (no collision monitor in this subset) until they touch
        assert time.monotonic() < deadline, "r1 never reached r2"
        r1.cmd.put(codec.encode(Twist2D(vx=0.2, stamp=r1.sim_now)))
        time.sleep(0.02)
    wait_for_sync(lambda: r2.truth.collided, timeout_s=10, message="r2 never reported the contact")
    a, b = r1.truth, r2.truth
    assert (a.contact_with, b.contact_with) == ("r2", "r1")
    gap = math.hypot(a.pose.x - b.pose.x, a.pose.y - b.pose.y) - 2 * RADIUS_M
    assert -0.005 <= gap < 0.05  # stopped at the touch, not inside the other chassis
    assert b.pose.x == pytest.approx(0.0, abs=0.01)  # r2 was not pushed
    # r1's laser now sees r2's chassis just ahead
    assert r1.range_ahead_m(a.stamp) == pytest.approx(gap + 2 * RADIUS_M - RADIUS_M - LASER_X_M, abs=0.05)
    assert "r1.drive" in stack.output() and "r2.lidar" in stack.output()
    assert stack.pid("r2.drive") != stack.pid("r1.drive")


# --------------------------------------------------------------------------- the long suite: whole scenarios


def run_scenario_file(path: Path, tmp_path: Path, *extra: str) -> tuple[int, dict, str]:
    """``zagv scenario run`` in a subprocess; (exit code, its JSON, its output)."""
    import json
    import subprocess
    import sys

    out = tmp_path / "result.json"
    proc = subprocess.run([sys.executable, "-m", "services.cli", "scenario", "run", str(path), "--json", str(out),
                           "--run-dir", str(tmp_path / "run"), "--goal-timeout", "600", *extra],
                          capture_output=True, text=True, cwd=Path(__file__).resolve().parents[1], timeout=3600)
    text = proc.stdout + proc.stderr
    return proc.returncode, json.loads(out.read_text()) if out.exists() else {}, text


def assert_all_reached_without_contact(code: int, result: dict, text: str, n_robots: int) -> None:
    assert result, f"no result:\n{text[-4000:]}"
    assert len(result["robots"]) == n_robots
    goals = [g for r in result["robots"] for g in r["goals"]]
    assert all(g["reached"] for g in goals), text[-4000:]
    assert result["contacts"] == [], text[-4000:]
    assert result["deadlocks"] == [], text[-4000:]
    assert code == 0, text[-4000:]


REPO = Path(__file__).resolve().parents[1]


@pytest.mark.long
def test_three_robots_cross_the_hall_without_contact(tmp_path) -> None:
    code, result, text = run_scenario_file(REPO / "scenarios" / "crossing_fleet.toml", tmp_path)
    assert_all_reached_without_contact(code, result, text, 3)
    print(text)


#: three robots on Nav2's depot map: r1 in the west, r2 along the east side, r3 across the whole floor and back,
#: its route crossing r1's; the depot goals of scenarios/depot.toml and two more in the open middle aisle
DEPOT_FLEET = """
speed = 1.0
[[robots]]
id = "r1"
start = [1.6, 6.0, 0.0]
[[robots.goals]]
id = "north-west"
pose = [7.5, 8.6, 0.0]
[[robots.goals]]
id = "south-west"
pose = [7.8, 1.9, -1.57]
[[robots]]
id = "r2"
start = [27.9, 12.7, 1.57]
[[robots.goals]]
id = "south-east"
pose = [22.3, 1.5, 3.14]
[[robots.goals]]
id = "north-east"
pose = [27.9, 12.7, 1.57]
[[robots]]
id = "r3"
start = [19.0, 8.4, 3.14]
[[robots.goals]]
id = "west"
pose = [3.6, 8.4, 3.14]
[[robots.goals]]
id = "centre"
pose = [19.0, 8.4, 0.0]
"""


@pytest.mark.long
def test_three_robots_in_the_depot_without_contact(tmp_path, shared_dir) -> None:
    depot = shared_dir / "data" / "maps" / "nav2_depot" / "depot.yaml"
    if not depot.is_file():
        pytest.skip(f"the depot map is not in the development data ({depot})")
    scenario = tmp_path / "depot_fleet.toml"
    scenario.write_text(f'map = "{depot}"\n' + DEPOT_FLEET)
    code, result, text = run_scenario_file(scenario, tmp_path)
    assert_all_reached_without_contact(code, result, text, 3)
    print(text)


@pytest.mark.long
def test_the_later_robot_waits_for_the_narrow_passage(tmp_path) -> None:
    code, result, text = run_scenario_file(REPO / "scenarios" / "passage_fleet.toml", tmp_path)
    assert result, text[-4000:]
    # never pushing in: no contact whatever else happens; a deadlock would be reported in the result, not hidden
    assert result["contacts"] == [], text[-4000:]
    assert_all_reached_without_contact(code, result, text, 2)
    print(text)


def test_a_fleet_robots_composed_services_are_found_in_that_robots_container(tmp_path) -> None:
    """``r2.lidar`` runs in ``r2.components`` (the container's line names its services without the robot), never
    in another robot's; a service started on its own is its own process."""
    from services.launch.stack_process import Stack

    stack = Stack(tmp_path, None, fleet_size=3)
    for n, rid in enumerate(("r1", "r2", "r3")):
        stack.lines += [f"zagv          | started {rid}.drive (pid {100 + n})",
                        f"zagv          | started {rid}.components (pid {200 + n})",
                        f"{rid}.components | 16:27:54.5 INFO {rid}.components [zagv.container]: running lidar, "
                        "safety, localization, nav, recorder in one process"]
    assert stack.process_of("r2.lidar") == "r2.components"
    assert stack.process_of("r3.recorder") == "r3.components"
    assert stack.process_of("r1.drive") == "r1.drive"
    assert {stack.pid(f"r2.{s}") for s in ("drive", "lidar", "safety", "nav")} == {101, 201}
