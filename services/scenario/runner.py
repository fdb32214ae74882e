"""``zagv scenario run FILE [--json OUT] [--plots DIR]``: run navigation goals in the simulator and report the
final-pose errors against ground truth (the paper's Table 3).

Scenario TOML (keys fixed):

    world = "corridor"            # a built-in sim world, or
    map = "maps/depot.yaml"       # any ROS map YAML (relative to the scenario file, else --maps-dir, else the
                                  # current folder)
    start = [0.0, 0.0, 0.0]       # x, y (m), theta (rad)
    repeats = 10
    speed = 4.0                   # sim speed factor (sim s per wall s)
    name = "corridor_table3"      # optional (default: the file name without .toml); description = "..." optional
    [[goals]]
    pose = [3.0, 0.1, 1.57]
    id = "1"                      # optional
    [[dynamic_obstacles]]
    rect = [9.0, 1.6, 10.0, 3.0]  # xmin, ymin, xmax, ymax (m)
    during_goal = 7               # 1-based index of the goal during whose leg it appears (removed after the leg)
    appear_after_s = 5.0          # sim seconds after that goal is sent
    [mapping]                     # optional: build the map first by jogging, then run the goals on it
    route = [[4.0, 0.1, 0.0], [4.0, 0.1, 3.1]]  # waypoints [x, y, theta] jogged in order from `start` (world frame)
    save_as = "corridor_built"    # optional map name (default "<name>_built"): letters, digits, '_', '-', '.'
    jog_speed_mps = 0.2           # optional, > 0 and <= the robot's vx_max_mps and vy_max_mps (default: vx_max_mps)
    map_error_allowance_m = 0.1   # optional (default 0): how far the built map may lie from the world at a goal

The stack runs headless on its own free ports. Each repeat starts with the robot teleported to ``start`` and the
localization told so. A goal counts as reached when nav reports ``succeeded``; the error is the ground-truth pose
0.5 s (sim) after nav's result, minus the target, theta wrapped to (-pi, pi]. A goal counts as reached when that
ground-truth error is within the robot's goal tolerance (Table 2: 0.05 m, 0.05 rad), whatever nav claimed; a goal
nav reports ``succeeded`` outside it is printed and counted. JSON: ``{"runs": [{"run": 1, "goals": [{"id",
"target", "reached", "claimed", "nav_error", "final", "error", "time_s", "recoveries", "collisions", "driven_m",
"loc_error_max_m", "loc_error_rms_m"}]}]}`` (localization error: |estimate - truth| at every odometry stamp of the
leg, the truth interpolated to that stamp).

With ``[mapping]`` (the paper's mapping workflow, services/scenario/mapping.py) the stack starts in mapping mode
(``zagv up --mapping``, SLAM's map frame and the simulated robot both at ``start``); the simulated operator jogs the
route by ``cmd_vel`` while watching ``sim/ground_truth``, then the map is saved (``localization/save_map``), scored
against the world's ground-truth map (occupied-cell F1), localization switches to AMCL on it (``localization/mode``)
and, once nav's costmap follows the saved map, the goals run as above. The JSON gains ``"mapping": {"route_length_m",
"driven_m", "jog_time_s", "jog_wall_s", "map_yaml", "map_f1": {"precision", "recall", "f1", ...}, "nav_map_wait_s",
"late_jog_commands"}`` (jog commands sent more than the drive's 0.2 s command timeout after the previous one: the sim
ran faster than the machine kept up with). A SLAM map drifts against the world by a few centimetres over tens of
metres, and that drift is part of the ground-truth error; with ``map_error_allowance_m`` a goal counts as reached
when the ground-truth error is within the tolerance plus the allowance and the error in the built map's frame
(localization estimate - target, ``map_frame_error`` in the JSON) is within the tolerance.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from proto import messages as m
from proto.keys import Keys
from services.common.query import QueryError
from services.common.se2 import wrap_angle
from services.scenario.client import Client, Leg, localization_errors_m, wait_until
from services.scenario.model import Goal, Scenario

TERMINAL = ("succeeded", "failed", "canceled")


# --------------------------------------------------------------------------- running


#: wall seconds a goal request is re-sent for while nav's reply does not arrive
GOAL_REQUEST_DEADLINE_S = 60.0
#: wall seconds one ask of a scenario request waits for its answer
ATTEMPT_TIMEOUT_S = 20.0


async def query_until(c: Client, name: str, req: m.Message, deadline_s: float) -> Any:
    """``c.query`` asked again while nothing answers (a service busy relocalizing on a loaded machine), until
    ``deadline_s`` of wall time; the last QueryError then. Each ask waits up to ``ATTEMPT_TIMEOUT_S``: on a
    loaded machine an answer can take seconds, and one that comes late is still the answer."""
    deadline = time.monotonic() + deadline_s
    while True:
        try:
            return await c.query(name, req, timeout_s=max(1.0, min(ATTEMPT_TIMEOUT_S, deadline - time.monotonic())))
        except QueryError:
            if time.monotonic() > deadline:
                raise
            await asyncio.sleep(0.5)


async def place_robot(c: Client, pose: tuple[float, float, float]) -> None:
    """Teleport the simulated robot and tell localization where it is; wait for the estimate to agree."""
    await wait_until(lambda: c.odom_count > 5, "no odometry (is drive running and its CAN link up?)", 90.0)
    p = m.Pose2D(x=pose[0], y=pose[1], theta=pose[2])
    r = await query_until(c, "sim/teleport", m.TeleportRequest(pose=p), 60.0)
    if not r.ok:
        raise RuntimeError(f"sim/teleport refused: {r.message}")
    await c.sim_sleep(1.0)  # scans taken before the jump are through the pipeline
    cov = [0.0025, 0, 0, 0, 0.0025, 0, 0, 0, 0.003]
    for attempt in range(1, 7):
        r = await query_until(c, "localization/initial_pose", m.InitialPoseRequest(pose=p, covariance=cov), 60.0)
        if not r.ok:
            raise RuntimeError(f"localization/initial_pose refused: {r.message}")
        count_at_set = c.pose_count

        def localized(converged: bool) -> bool:  # a pose published after the reset, near the start
            e = c.pose
            return (e is not None and c.pose_count > count_at_set  # noqa: B023
                    and (e.state == "tracking" or not converged)
                    and math.hypot(e.pose.x - pose[0], e.pose.y - pose[1]) < 0.1
                    and abs(wrap_angle(e.pose.theta - pose[2])) < 0.1)

        try:  # localization converges at rest (state "tracking"); a map where it cannot settle keeps the near pose
            with contextlib.suppress(RuntimeError):
                await wait_until(lambda: localized(True), "localization did not converge", 10.0)
            await wait_until(lambda: localized(False), f"localization did not report a pose near the start {pose}",
                             10.0)
            break
        except RuntimeError:
            if attempt == 6:
                raise
    # scans taken between the teleport and the reset were placed with the old pose: not obstacles of this world
    with contextlib.suppress(QueryError):
        await c.query("nav/clear_costmaps", m.Empty())
    await c.sim_sleep(1.0)


def judge_leg(result: dict, state: str, nav_error: str, leg: Leg, collisions: int, xy_tol_m: float,
              yaw_tol_rad: float, map_error_allowance_m: float = 0.0) -> None:
    """Fill a goal's result: ``reached`` by the ground truth (|error xy| < xy_tol_m and |error theta| <
    yaw_tol_rad), whatever nav ``claimed``; the leg's collisions, recoveries, driven distance (ground truth) and
    the max and RMS of |localization estimate - truth| over the leg (``localization_errors_m``).

    On a map built in the same run (``map_error_allowance_m`` > 0) the built map's own drift against the world is
    part of the ground-truth error, so the world error may exceed the tolerance by the allowance, and the error in
    the built map's frame (``map_frame_error`` = estimate - target) must be within the tolerance."""
    result["claimed"] = state
    result["nav_error"] = nav_error
    result["collisions"] = collisions
    e = result["error"]
    result["reached"] = bool(e[0] is not None and math.hypot(e[0], e[1]) < xy_tol_m + map_error_allowance_m
                             and abs(e[2]) < yaw_tol_rad)
    if map_error_allowance_m > 0:
        f = result.get("map_frame_error")
        result["reached"] = bool(result["reached"] and f is not None and math.hypot(f[0], f[1]) < xy_tol_m
                                 and abs(f[2]) < yaw_tol_rad)
    tr = np.asarray(leg.trace, dtype=float).reshape(-1, 7)
    result["driven_m"] = round(float(np.hypot(*np.diff(tr[:, 1:3], axis=0).T).sum()), 3) if len(tr) > 1 else 0.0
    le = localization_errors_m(leg)
    if len(le):
        result["loc_error_max_m"] = round(float(le.max()), 4)
        result["loc_error_rms_m"] = round(float(np.sqrt(np.mean(le ** 2))), 4)




def unreached_goal_result(goal: Goal, claimed: str, why: str) -> dict:
    """The result of a goal not (yet) reached: ``claimed`` says what became of it ("rejected", "not sent", "not
    run"), ``why`` is nav's or the runner's reason."""
    return {"id": goal.id, "target": list(goal.pose), "reached": False, "final": [None] * 3, "error": [None] * 3,
            "time_s": 0.0, "claimed": claimed, "nav_error": why, "recoveries": 0, "collisions": 0,
            "driven_m": 0.0, "loc_error_max_m": None, "loc_error_rms_m": None}


async def run_goal(c: Client, sc: Scenario, run: int, index: int, goal: Goal, timeout_s: float,
                   legs: list[Leg] | None, xy_tol_m: float = 0.05, yaw_tol_rad: float = 0.05,
                   map_error_allowance_m: float = 0.0) -> dict:
    leg = Leg(run, goal, c.sim_time)
    c.leg = leg
    obstacles = [o for o in sc.dynamic_obstacles if o.during_goal == index]
    placed: list[str] = []
    req = m.GoalRequest(pose=m.Pose2D(x=goal.pose[0], y=goal.pose[1], theta=goal.pose[2]),
                        id=f"r{run}g{goal.id}")
    deadline = time.monotonic() + GOAL_REQUEST_DEADLINE_S
    while True:  # a reply lost or late under load: ask again (the same id and pose: nav keeps the goal running)
        try:
            reply: m.GoalReply = await c.query("nav/goal", req, timeout_s=ATTEMPT_TIMEOUT_S)
            break
        except QueryError:
            if time.monotonic() > deadline:
                raise
            await asyncio.sleep(0.5)
    while not reply.accepted and ("no robot pose" in reply.reason or "no map" in reply.reason) \
            and time.monotonic() < deadline:
        await asyncio.sleep(0.2)  # nav has not yet seen odometry, map->odom or the map
        reply = await c.query("nav/goal", req, timeout_s=ATTEMPT_TIMEOUT_S)
    t0 = c.sim_time
    collisions_before = c.collisions
    result: dict[str, Any] = unreached_goal_result(goal, "rejected", reply.reason)
    if not reply.accepted:
        print(f"scenario: run {run} goal {goal.id} rejected: {reply.reason}", flush=True)
        c.leg = None
        return result
    state, error = "", ""
    try:
        while True:
            for k, o in enumerate(obstacles):
                oid = f"scenario{k}"
                if oid not in placed and c.sim_time - t0 >= o.appear_after_s:
                    rr = await c.query("sim/obstacles", m.ObstacleRequest(action="add", id=oid, rect=list(o.rect)))
                    if rr.ok:
                        placed.append(oid)
                        leg.obstacles.append(o.rect)
                    else:
                        print(f"scenario: obstacle {oid} refused: {rr.message}", flush=True)
                        placed.append(oid)
            st = c.status
            if st is not None and st.goal_id == reply.goal_id and st.state in TERMINAL:
                state, error = st.state, st.error
                result["recoveries"] = st.recoveries
                break
            if c.sim_time - t0 > timeout_s:
                await c.query("nav/cancel", m.CancelRequest(goal_id=reply.goal_id))
                state, error = "timeout", f"no result within {timeout_s:.0f} s (sim)"
                break
            c.status_changed.clear()
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(c.status_changed.wait(), 0.1)
        result["time_s"] = round(c.sim_time - t0, 3)
        await c.sim_sleep(0.5)
        if c.truth is not None:
            p = c.truth.pose
            result["final"] = [p.x, p.y, p.theta]
            result["error"] = [p.x - goal.pose[0], p.y - goal.pose[1], wrap_angle(p.theta - goal.pose[2])]
            est = c.estimate()
            if est is not None:  # how far localization was off at the end (diagnostic, not in the JSON)
                c.localization_errors.append((est[0] - p.x, est[1] - p.y, wrap_angle(est[2] - p.theta)))
                if map_error_allowance_m > 0:
                    result["map_frame_error"] = [round(est[0] - goal.pose[0], 4), round(est[1] - goal.pose[1], 4),
                                                 round(wrap_angle(est[2] - goal.pose[2]), 4)]
        judge_leg(result, state, error, leg, c.collisions - collisions_before, xy_tol_m, yaw_tol_rad,
                  map_error_allowance_m)
        if state != "succeeded":
            print(f"scenario: run {run} goal {goal.id}: {state} {error}", flush=True)
        elif not result["reached"]:
            print(f"scenario: run {run} goal {goal.id}: nav reported succeeded but the robot is outside the "
                  f"tolerance ({result['error'][0]:+.3f}, {result['error'][1]:+.3f}, {result['error'][2]:+.3f})",
                  flush=True)
    finally:
        for oid in placed:
            with contextlib.suppress(QueryError):
                await c.query("sim/obstacles", m.ObstacleRequest(action="remove", id=oid))
        c.leg = None
        if legs is not None:
            legs.append(leg)
        if leg.obstacles:
            c.detours.append(leg.final_plan is not None)
    return result


async def run_scenario(sc: Scenario, session, keys: Keys, *, goal_timeout_s: float, plots: bool,
                       progress=print, truth_yaml: str | Path | None = None,
                       ) -> tuple[list[dict], list[Leg], int, list[bool], Any]:
    """Run the mapping phase (when the scenario has one; ``truth_yaml`` is the world's ground-truth map) and the
    goals; returns (runs, plotted legs, collisions, detours per obstacle leg, MappingResult or None)."""
    from services.common.robot import RobotSpec

    spec = RobotSpec()
    loop = asyncio.get_running_loop()
    c = Client(session, keys, loop)
    legs: list[Leg] = []
    runs = []
    mapping = None
    try:
        # the simulator builds a large map's world (2048x2048 cells: over a minute on a loaded machine) after its
        # health token is up
        deadline = time.monotonic() + 240
        while c.truth is None or c.sim_time <= 0:
            if time.monotonic() > deadline:
                raise RuntimeError("no sim/ground_truth within 240 s")
            await asyncio.sleep(0.05)
        if sc.mapping is not None:
            from services.common.robot import RobotSpec
            from services.scenario.mapping import run_mapping

            if truth_yaml is None:
                raise RuntimeError("the mapping phase needs the ground-truth map")
            mp = sc.mapping
            mapping = await run_mapping(c, sc.start, mp.route, mp.save_as, mp.jog_speed_mps, truth_yaml, RobotSpec(),
                                        progress)
        for run in range(1, sc.repeats + 1):
            try:
                await place_robot(c, sc.start)
            except (RuntimeError, QueryError) as exc:  # report the runs done so far
                progress(f"scenario: stopped before run {run}: {exc}")
                c.aborted = True
                break
            goals = []
            for k, goal in enumerate(sc.goals, 1):
                try:
                    res = await run_goal(c, sc, run, k, goal, goal_timeout_s, legs if plots and run == 1 else None,
                                         spec.goal_xy_tolerance_m, spec.goal_yaw_tolerance_rad,
                                         sc.mapping.map_error_allowance_m if sc.mapping is not None else 0.0)
                except QueryError as exc:  # this goal never reached nav: it counts as not reached, the run goes on
                    c.leg = None
                    res = unreached_goal_result(goal, "not sent", str(exc))
                goals.append(res)
                err = ", ".join(f"{v:+.3f}" if v is not None else "-" for v in res["error"])
                loc = ", ".join(f"{v:+.3f}" for v in c.localization_errors[-1]) if c.localization_errors else "-"
                progress(f"scenario: run {run} goal {goal.id}: {'reached' if res['reached'] else 'NOT reached'}"
                         f" error {err} in {res['time_s']:.1f} s (localization estimate - truth: {loc})")
            runs.append({"run": run, "goals": goals})
    finally:
        c.close()
    if c.aborted:
        runs.append({"run": len(runs) + 1, "goals": [
            {"id": g.id, "target": list(g.pose), "reached": False, "final": [None] * 3, "error": [None] * 3,
             "time_s": 0.0} for g in sc.goals]})
    return runs, legs, c.collisions, c.detours, mapping
