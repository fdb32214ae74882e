"""Goal execution end to end without processes: the Navigator drives a kinematic holonomic robot (first-order
velocity response within the acceleration limits) that sees its world through a ray-cast 270° laser."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.common.robot import RobotSpec
from services.common.se2 import wrap_angle
from services.nav.config import NavConfig
from services.nav.costmap import ScanObservation
from services.nav.navigator import Navigator

RES = 0.05


def room_world(free_rects: list[list[float]], extent: list[float], solid: list[list[float]] = ()) -> tuple:
    x0, y0, x1, y1 = extent
    w, h = int(round((x1 - x0) / RES)), int(round((y1 - y0) / RES))
    xs = x0 + (np.arange(w) + 0.5) * RES
    ys = y0 + (np.arange(h) + 0.5) * RES
    gx, gy = np.meshgrid(xs, ys)
    occ = np.full((h, w), 100, dtype=np.int8)
    for r in free_rects:
        occ[(gx >= r[0]) & (gx <= r[2]) & (gy >= r[1]) & (gy <= r[3])] = 0
    for r in solid:
        occ[(gx >= r[0]) & (gx <= r[2]) & (gy >= r[1]) & (gy <= r[3])] = 100
    return occ, x0, y0


class KinematicSim:
    """Holonomic robot + 270° laser (541 beams, 20 m) ray-cast in an occupancy grid that may change."""

    def __init__(self, occ: np.ndarray, x0: float, y0: float, pose: tuple[float, float, float]) -> None:
        self.occ, self.x0, self.y0 = occ.copy(), x0, y0
        self.pose = np.array(pose, dtype=float)
        self.vel = np.zeros(3)
        self.t = 0.0
        self.collided = False
        self.robot = RobotSpec()

    def add_box(self, rect: list[float]) -> None:
        h, w = self.occ.shape
        ys = self.y0 + (np.arange(h) + 0.5) * RES
        xs = self.x0 + (np.arange(w) + 0.5) * RES
        gx, gy = np.meshgrid(xs, ys)
        self.occ[(gx >= rect[0]) & (gx <= rect[2]) & (gy >= rect[1]) & (gy <= rect[3])] = 100

    def occupied(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        j = np.floor((x - self.x0) / RES).astype(int)
        i = np.floor((y - self.y0) / RES).astype(int)
        ok = (i >= 0) & (i < self.occ.shape[0]) & (j >= 0) & (j < self.occ.shape[1])
        out = np.ones(np.shape(x), dtype=bool)
        out[ok] = self.occ[i[ok], j[ok]] >= 50
        return out

    def scan(self) -> ScanObservation:
        mount = (0.45, 0.0)
        c, s = math.cos(self.pose[2]), math.sin(self.pose[2])
        ox, oy = self.pose[0] + c * mount[0], self.pose[1] + s * mount[0]
        rel = np.linspace(-3 * math.pi / 4, 3 * math.pi / 4, 541)
        a = self.pose[2] + rel
        t = np.arange(0.05, 8.0, RES / 2)
        hit = self.occupied(ox + np.cos(a)[:, None] * t, oy + np.sin(a)[:, None] * t)
        first = np.where(hit.any(axis=1), t[np.argmax(hit, axis=1)], np.inf)
        return ScanObservation(ox, oy, a, first, 0.05, 8.0)

    def step(self, cmd: tuple[float, float, float], dt: float) -> None:
        cmd = np.asarray(cmd)
        assert np.all(np.isfinite(cmd))
        acc = np.array([self.robot.ax_max_mps2, self.robot.ay_max_mps2, self.robot.alpha_max_radps2]) * dt
        self.vel += np.clip(cmd - self.vel, -acc, acc)
        c, s = math.cos(self.pose[2]), math.sin(self.pose[2])
        self.pose += dt * np.array([c * self.vel[0] - s * self.vel[1], s * self.vel[0] + c * self.vel[1],
                                    self.vel[2]])
        self.t += dt
        a = np.linspace(0, 2 * math.pi, 64, endpoint=False)
        r = self.robot.chassis_radius_m
        if self.occupied(self.pose[0] + r * np.cos(a), self.pose[1] + r * np.sin(a)).any():
            self.collided = True


def drive(nav: Navigator, sim: KinematicSim, limit_s: float, scans: bool = True, on_step=None,
          stop_when=None) -> list[str]:
    """Run the control loop at 20 Hz until the goal ends (or ``stop_when()``), answering localization's updates at
    once; the states seen, in order."""
    dt = 0.05
    states: list[str] = []
    end = sim.t + limit_s
    k = 0
    while sim.t < end:
        pose = tuple(sim.pose)
        if scans and k % 2 == 0:
            nav.add_scan(sim.scan())
        if k % 4 == 0:
            nav.update_costmaps(pose, "local")
        if k % 10 == 0:
            nav.update_costmaps(pose, "global")
        if nav.plan_due(sim.t):
            nav.apply_plan(sim.t, nav.compute_plan(nav.make_request(pose)), pose)
        cmd = nav.step(sim.t, pose)
        if nav.localization_request:  # a localization that answers at once (the pose here is exact)
            nav.localization_request = False
            nav.localization_updated(sim.t)
        if nav.state not in states:
            states.append(nav.state)
        if nav.state in ("succeeded", "failed", "canceled") or (stop_when is not None and stop_when()):
            break
        if on_step is not None:
            on_step(sim)
        sim.step(cmd, dt)
        k += 1
    return states


CORRIDOR = dict(free_rects=[[-2.0, -1.4, 6.0, 1.6], [-2.0, 1.6, 16.0, 4.9]], extent=[-2.5, -2.0, 16.5, 5.5])


def make(pose: tuple[float, float, float], **cfg) -> tuple[Navigator, KinematicSim]:
    occ, x0, y0 = room_world(**CORRIDOR)
    nav = Navigator(NavConfig(**cfg), RobotSpec())
    nav.set_map(occ, RES, x0, y0)
    return nav, KinematicSim(occ, x0, y0, pose)


def pose_error(sim: KinematicSim, goal: tuple[float, float, float]) -> tuple[float, float, float]:
    e = sim.pose - np.asarray(goal)
    return float(e[0]), float(e[1]), wrap_angle(float(e[2]))


@pytest.mark.parametrize("goal", [(3.0, 0.1, 1.57), (3.0, 3.5, 0.0), (1.0, -0.5, -2.5)])
def test_reaches_goal_within_two_centimetres_and_radians(goal: tuple[float, float, float]) -> None:
    nav, sim = make((0.0, 0.0, 0.0))
    ok, gid, reason = nav.start_goal(0.0, goal)
    assert ok, reason
    drive(nav, sim, 120.0)
    assert nav.state == "succeeded", nav.error
    ex, ey, eth = pose_error(sim, goal)
    assert abs(ex) <= 0.02 and abs(ey) <= 0.02 and abs(eth) <= 0.02, (ex, ey, eth)
    assert not sim.collided
    assert [e[:2] for e in nav.take_finished()] == [(gid, "succeeded")]


def test_turns_in_place_first_when_the_goal_lies_behind() -> None:
    nav, sim = make((3.0, 3.2, 0.0))
    ok, _, _ = nav.start_goal(0.0, (-1.0, 3.2, math.pi))
    assert ok
    positions = []
    states = drive(nav, sim, 120.0, on_step=lambda s: positions.append((nav.state, s.pose.copy())))
    assert nav.state == "succeeded", nav.error
    assert [s for s in states if s != "planning"][:2] == ["rotating", "driving"]
    turning = [p for st, p in positions if st == "rotating"]
    # while it turns towards the path it stays on the spot
    first_drive = next(p for st, p in positions if st == "driving")
    assert np.hypot(*(first_drive[:2] - np.array([3.0, 3.2]))) < 0.05
    assert len(turning) > 20


@pytest.mark.slow
def test_replans_around_a_box_that_appears_on_the_path() -> None:
    nav, sim = make((1.0, 3.5, 0.0))
    goal = (14.0, 3.5, 0.0)
    ok, _, _ = nav.start_goal(0.0, goal)
    assert ok
    box = [6.0, 1.6, 7.0, 3.0]
    added = []
    paths_before = []

    def appear(s: KinematicSim) -> None:
        if not added and s.t > 5.0:
            paths_before.append(nav.path.copy())
            s.add_box(box)
            added.append(s.t)

    drive(nav, sim, 200.0, on_step=appear)
    assert nav.state == "succeeded", nav.error
    assert not sim.collided
    # the path first ran straight through the box; the final one passes north of it
    before = paths_before[0]
    inside = (before[:, 0] > 6.0) & (before[:, 0] < 7.0) & (before[:, 1] < 3.0 + 0.63)
    assert inside.any()
    ex, ey, eth = pose_error(sim, goal)
    assert abs(ex) <= 0.02 and abs(ey) <= 0.02 and abs(eth) <= 0.02


def test_unreachable_goal_fails_with_a_reason_after_recoveries() -> None:
    nav, sim = make((1.0, 3.5, 0.0), max_recoveries=2)
    # a wall across the corridor, in the world but not in the map: only the laser sees it
    sim.add_box([8.0, 1.6, 8.3, 4.9])
    ok, _, _ = nav.start_goal(0.0, (12.0, 3.5, 0.0))
    assert ok
    states = drive(nav, sim, 400.0)
    assert nav.state == "failed"
    assert "recoveries" in nav.error and ("no path" in nav.error or "progress" in nav.error
                                          or "trajectory" in nav.error)
    assert "recovering" in states
    assert not sim.collided


def test_goal_rejections_name_the_reason() -> None:
    nav, _ = make((0.0, 0.0, 0.0))
    assert "inside an obstacle" in nav.start_goal(0.0, (3.0, -1.8, 0.0))[2]
    assert "outside the map" in nav.start_goal(0.0, (50.0, 0.0, 0.0))[2]
    assert "closer than the robot's radius" in nav.start_goal(0.0, (3.0, 4.6, 0.0))[2]
    assert "not finite" in nav.start_goal(0.0, (math.nan, 0.0, 0.0))[2]
    fresh = Navigator(NavConfig(), RobotSpec())
    assert "no map" in fresh.start_goal(0.0, (1.0, 1.0, 0.0))[2]


def test_cancel_stops_the_robot() -> None:
    nav, sim = make((0.0, 0.0, 0.0))
    ok, gid, _ = nav.start_goal(0.0, (3.0, 3.5, 0.0))
    assert ok
    drive(nav, sim, 5.0)
    assert nav.state in ("driving", "rotating")
    assert nav.cancel("other")[0] is False
    assert nav.cancel(gid)[0] is True
    assert nav.state == "canceled"
    assert nav.step(sim.t, tuple(sim.pose)) == (0.0, 0.0, 0.0)


def test_the_active_goal_sent_again_keeps_running_and_a_new_one_preempts_it() -> None:
    """A client re-sends a goal whose reply was lost or late (same id and pose): nav keeps it as it is."""
    nav, sim = make((0.0, 0.0, 0.0))
    ok, gid, _ = nav.start_goal(0.0, (3.0, 3.5, 0.0), "g1")
    assert ok and gid == "g1"
    drive(nav, sim, 5.0)
    state, started, seq = nav.state, nav.goal.started_at, nav.goal.seq
    assert state in ("driving", "rotating")
    assert nav.start_goal(sim.t, (3.0, 3.5, 0.0), "g1") == (True, "g1", "")
    assert (nav.state, nav.goal.started_at, nav.goal.seq) == (state, started, seq) and not nav.finished
    assert nav.start_goal(sim.t, (3.0, 3.0, 0.0), "g1")[0]  # same id, another pose: a new goal
    assert nav.finished[-1] == ("g1", "canceled", "preempted by goal g1") and nav.state == "planning"


def test_waypoints_pause_resume_skip_and_results() -> None:
    nav, sim = make((0.0, 0.0, 0.0))
    wps = [("a", (1.5, 0.0, 0.0)), ("b", (3.0, 0.0, 0.0)), ("c", (3.0, 3.0, 1.57))]
    ok, sid, reason = nav.start_sequence(0.0, wps, "")
    assert ok, reason
    seq = nav.sequence
    assert seq is not None
    drive(nav, sim, 60.0, stop_when=lambda: len(seq.results) == 1)  # waypoint a done, the sequence goes on with b
    assert seq.results[0]["id"] == "a" and seq.results[0]["reached"]
    assert seq.index == 1 and nav.state == "planning"
    assert nav.control_sequence(sim.t, "pause")[0]
    assert nav.state == "idle" and nav.step(sim.t, tuple(sim.pose)) == (0.0, 0.0, 0.0)
    assert nav.control_sequence(sim.t, "resume")[0]
    assert nav.control_sequence(sim.t, "skip")[0]
    assert seq.results[1]["skipped"] and seq.index == 2
    drive(nav, sim, 120.0)
    assert nav.state == "succeeded"
    assert [r["id"] for r in seq.results] == ["a", "b", "c"]
    assert seq.results[2]["reached"] and abs(seq.results[2]["error"][0]) < 0.03
    assert nav.control_sequence(sim.t, "skip")[0] is False  # finished
    ok, _, reason = nav.start_sequence(sim.t, [("x", (3.0, -1.8, 0.0))], "")
    assert not ok and "waypoint 1" in reason


def test_polygon_footprint_reaches_a_goal() -> None:
    nav, sim = make((0.0, 0.0, 0.0), footprint=[[0.45, 0.4], [-0.45, 0.4], [-0.45, -0.4], [0.45, -0.4]])
    assert not nav.footprint.is_circle
    goal = (3.0, 3.3, 1.57)
    ok, _, reason = nav.start_goal(0.0, goal)
    assert ok, reason
    drive(nav, sim, 150.0)
    assert nav.state == "succeeded", nav.error
    ex, ey, eth = pose_error(sim, goal)
    assert abs(ex) <= 0.02 and abs(ey) <= 0.02 and abs(eth) <= 0.02


def test_settled_robot_asks_localization_and_corrects_odometry_drift() -> None:
    """Nav sees the pose 2 cm off (odometry drift since the last filter update) until it asks for an update."""
    nav, sim = make((0.0, 3.2, 0.0))
    goal = (2.0, 3.2, 0.0)
    assert nav.start_goal(0.0, goal)[0]
    drift = np.array([0.02, 0.0, 0.0])
    requests = []
    dt = 0.05
    while sim.t < 90.0 and nav.state not in ("succeeded", "failed"):
        seen = tuple(sim.pose + drift)
        if nav.plan_due(sim.t):
            nav.apply_plan(sim.t, nav.compute_plan(nav.make_request(seen)), seen)
        nav.update_costmaps(seen, "local")
        cmd = nav.step(sim.t, seen)
        if nav.localization_request:
            nav.localization_request = False
            requests.append(sim.t)
            drift = np.zeros(3)  # the fresh estimate is right
            nav.localization_updated(sim.t)
        sim.step(cmd, dt)
    assert nav.state == "succeeded", nav.error
    assert len(requests) >= 1
    ex, ey, eth = pose_error(sim, goal)
    assert abs(ex) <= 0.006 and abs(ey) <= 0.006, (ex, ey)


def drive_with_answers(nav: Navigator, sim: KinematicSim, offset: np.ndarray, answer, t_max: float = 90.0) -> list:
    """Drive with the estimate ``sim.pose + offset``; ``answer(request_times, t)`` runs every step and may change
    ``offset`` in place and call the Navigator's answer methods. Returns the request times; fails when nav claims
    success while a request is unanswered."""
    requests: list[float] = []
    dt = 0.05
    while sim.t < t_max and nav.state not in ("succeeded", "failed"):
        seen = tuple(sim.pose + offset)
        if nav.plan_due(sim.t):
            nav.apply_plan(sim.t, nav.compute_plan(nav.make_request(seen)), seen)
        nav.update_costmaps(seen, "local")
        cmd = nav.step(sim.t, seen)
        assert not (nav.state == "succeeded" and nav.goal is not None and nav.goal.loc_requested_at is not None), \
            "success claimed while a requested update was unanswered"
        if nav.localization_request:
            nav.localization_request = False
            requests.append(sim.t)
        answer(requests, sim.t)
        sim.step(cmd, dt)
    return requests


def test_a_late_answer_that_moves_the_estimate_is_waited_for_and_corrected_to() -> None:
    """The estimate nav settles on is 7 cm off; the requested update (a refinement at rest) moves it onto the truth
    but its answer comes 5 s of sim time later (a busy localization on a large map, a fast sim clock). Nav must
    hold until the answer, correct to it, and claim success only then: never on the estimate it was about to lose."""
    nav, sim = make((0.0, 3.2, 0.0))
    goal = (2.0, 3.2, 0.0)
    assert nav.start_goal(0.0, goal)[0]
    offset = np.array([0.0, 0.07, 0.0])
    answered: list[float] = []

    def answer(requests: list[float], t: float) -> None:
        if len(requests) > len(answered) and t >= requests[-1] + (5.0 if not answered else 0.1):
            offset[:] = 0.0  # the refined estimate is the truth
            answered.append(t)
            nav.localization_updated(t)

    requests = drive_with_answers(nav, sim, offset, answer)
    assert nav.state == "succeeded", nav.error
    assert len(requests) == 2 and answered[0] >= requests[0] + 5.0
    ex, ey, _ = pose_error(sim, goal)
    assert math.hypot(ex, ey) < 0.006, (ex, ey)


def test_an_update_localization_cannot_make_is_not_asked_for_again() -> None:
    nav, sim = make((0.0, 3.2, 0.0))
    goal = (2.0, 3.2, 0.0)
    assert nav.start_goal(0.0, goal)[0]

    def answer(requests: list[float], t: float) -> None:
        if requests and nav.goal is not None and nav.goal.loc_requested_at is not None:
            nav.localization_unavailable(t)

    requests = drive_with_answers(nav, sim, np.zeros(3), answer)
    assert nav.state == "succeeded", nav.error
    assert len(requests) == 1
