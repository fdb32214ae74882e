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

With ``[mapping]`` (the paper's mapping workflow, services/cli/scenario_mapping.py) the stack starts in mapping mode
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

import argparse
import asyncio
import contextlib
import json
import math
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from proto import codec
from proto import messages as m
from proto.keys import Keys
from services.cli.scenario_client import Client, Leg, localization_errors_m, wait_until
from services.cli.scenario_model import Goal, Scenario, ScenarioError, load_scenario
from services.common.query import QueryError, query
from services.common.se2 import wrap_angle

TERMINAL = ("succeeded", "failed", "canceled")


# --------------------------------------------------------------------------- report


def summarize(runs: list[dict]) -> list[dict]:
    """Per goal (in order): target, mean error over reached runs, reached count, mean time."""
    rows: dict[str, dict] = {}
    for run in runs:
        for g in run["goals"]:
            r = rows.setdefault(g["id"], {"id": g["id"], "target": g["target"], "errors": [], "times": [],
                                          "reached": 0, "total": 0})
            r["total"] += 1
            if g["reached"]:
                r["reached"] += 1
                r["errors"].append(g["error"])
                r["times"].append(g["time_s"])
    out = []
    for r in rows.values():
        e = np.asarray(r["errors"], dtype=float).reshape(-1, 3)
        out.append({"id": r["id"], "target": r["target"], "reached": r["reached"], "total": r["total"],
                    "mean_error": e.mean(axis=0).tolist() if len(e) else [math.nan] * 3,
                    "mean_abs_error": np.abs(e).mean(axis=0).tolist() if len(e) else [math.nan] * 3,
                    "mean_time_s": float(np.mean(r["times"])) if r["times"] else math.nan})
    return out


def leg_totals(runs: list[dict]) -> dict:
    """Totals over every goal of ``runs``: goals, reached (ground truth), claimed succeeded, claimed succeeded
    outside the tolerance, collisions, recoveries, localization error max and RMS (m, over all samples, RMS
    weighted by leg), time (s) and ground-truth distance driven (m), and time per metre (s/m) of the reached legs."""
    goals = [g for r in runs for g in r["goals"]]
    reached = [g for g in goals if g["reached"]]
    loc_max = [g.get("loc_error_max_m") for g in goals if g.get("loc_error_max_m") is not None]
    loc_rms = [g.get("loc_error_rms_m") for g in goals if g.get("loc_error_rms_m") is not None]
    t = sum(g["time_s"] for g in reached)
    d = sum(g.get("driven_m", 0.0) for g in reached)
    return {"goals": len(goals), "reached": len(reached),
            "claimed": sum(g.get("claimed", "succeeded" if g["reached"] else "") == "succeeded" for g in goals),
            "claimed_outside": sum(g.get("claimed") == "succeeded" and not g["reached"] for g in goals),
            "collisions": sum(g.get("collisions", 0) for g in goals),
            "recoveries": sum(g.get("recoveries", 0) for g in goals),
            "loc_error_max_m": max(loc_max) if loc_max else math.nan,
            "loc_error_rms_m": float(np.sqrt(np.mean(np.square(loc_rms)))) if loc_rms else math.nan,
            "time_s": t, "driven_m": d, "time_per_metre_s": t / d if d > 0 else math.nan}


def format_table(summary: list[dict]) -> str:
    w = max([len(str(r["id"])) for r in summary] + [4])
    head = f"{'goal':>{w}}  {'target (x, y, θ)':<24}  {'mean error x / y / θ':<26}  {'|error| x / y / θ':<26}  " \
           f"{'reached':>8}  {'time s':>7}"
    lines = [head, "-" * len(head)]
    for r in summary:
        t = "({:.2f}, {:.2f}, {:.2f})".format(*r["target"])
        e = "{:+.3f} / {:+.3f} / {:+.3f}".format(*r["mean_error"])
        a = "{:.3f} / {:.3f} / {:.3f}".format(*r["mean_abs_error"])
        lines.append(f"{r['id']:>{w}}  {t:<24}  {e:<26}  {a:<26}  {r['reached']:>3}/{r['total']:<4}  "
                     f"{r['mean_time_s']:>7.1f}")
    return "\n".join(lines)


# --------------------------------------------------------------------------- running


async def query_until(c: Client, name: str, req: m.Message, deadline_s: float) -> Any:
    """``c.query`` asked again while nothing answers (a service busy relocalizing on a loaded machine), until
    ``deadline_s`` of wall time; the last QueryError then."""
    deadline = time.monotonic() + deadline_s
    while True:
        try:
            return await c.query(name, req)
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


async def run_goal(c: Client, sc: Scenario, run: int, index: int, goal: Goal, timeout_s: float,
                   legs: list[Leg] | None, xy_tol_m: float = 0.05, yaw_tol_rad: float = 0.05,
                   map_error_allowance_m: float = 0.0) -> dict:
    leg = Leg(run, goal, c.sim_time)
    c.leg = leg
    obstacles = [o for o in sc.dynamic_obstacles if o.during_goal == index]
    placed: list[str] = []
    req = m.GoalRequest(pose=m.Pose2D(x=goal.pose[0], y=goal.pose[1], theta=goal.pose[2]),
                        id=f"r{run}g{goal.id}")
    deadline = time.monotonic() + 30.0
    while True:  # a reply lost under load: ask again (the same id, so nav takes it as the same goal)
        try:
            reply: m.GoalReply = await c.query("nav/goal", req)
            break
        except QueryError:
            if time.monotonic() > deadline:
                raise
            await asyncio.sleep(0.5)
    while not reply.accepted and ("no robot pose" in reply.reason or "no map" in reply.reason) \
            and time.monotonic() < deadline:
        await asyncio.sleep(0.2)  # nav has not yet seen odometry, map->odom or the map
        reply = await c.query("nav/goal", req)
    t0 = c.sim_time
    collisions_before = c.collisions
    result: dict[str, Any] = {"id": goal.id, "target": list(goal.pose), "reached": False, "final": [None] * 3,
              "error": [None] * 3, "time_s": 0.0, "claimed": "rejected", "nav_error": reply.reason,
              "recoveries": 0, "collisions": 0, "driven_m": 0.0, "loc_error_max_m": None, "loc_error_rms_m": None}
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
            from services.cli.scenario_mapping import run_mapping
            from services.common.robot import RobotSpec

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
                res = await run_goal(c, sc, run, k, goal, goal_timeout_s, legs if plots and run == 1 else None,
                                     spec.goal_xy_tolerance_m, spec.goal_yaw_tolerance_rad,
                                     sc.mapping.map_error_allowance_m if sc.mapping is not None else 0.0)
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


def draw_plots(legs: list[Leg], grid: m.OccupancyGrid | None, out_dir: Path) -> list[Path]:
    """Per leg: map + planned path + driven path as heading arrows; vx, vy, wz against time (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    files = []
    for k, leg in enumerate(legs, 1):
        tr = np.asarray(leg.trace, dtype=float).reshape(-1, 7)
        fig, ax = plt.subplots(figsize=(9, 6))
        if grid is not None and grid.width:
            data = codec.array(grid, "data").reshape(grid.height, grid.width)
            img = np.where(data < 0, 0.6, 1.0 - np.clip(data, 0, 100) / 100.0)
            ext = (grid.origin.x, grid.origin.x + grid.width * grid.resolution, grid.origin.y,
                   grid.origin.y + grid.height * grid.resolution)
            ax.imshow(img, cmap="gray", origin="lower", extent=ext, vmin=0, vmax=1)
        for r in leg.obstacles:
            ax.add_patch(plt.Rectangle((r[0], r[1]), r[2] - r[0], r[3] - r[1], color="orange", alpha=0.8,
                                       label="dynamic obstacle"))
        if leg.plan is not None and len(leg.plan):
            ax.plot(leg.plan[:, 0], leg.plan[:, 1], "b-", lw=1.5, label="global plan")
        if leg.final_plan is not None:
            ax.plot(leg.final_plan[:, 0], leg.final_plan[:, 1], "c--", lw=1.2, label="replanned around the obstacle")
        if len(tr):
            step = max(1, len(tr) // 60)
            s = tr[::step]
            ax.quiver(s[:, 1], s[:, 2], np.cos(s[:, 3]), np.sin(s[:, 3]), color="r", scale=40, width=0.003,
                      label="driven (heading)")
            pad = 2.0
            xs = np.concatenate([tr[:, 1], [leg.goal.pose[0]]])
            ys = np.concatenate([tr[:, 2], [leg.goal.pose[1]]])
            ax.set_xlim(xs.min() - pad, xs.max() + pad)
            ax.set_ylim(ys.min() - pad, ys.max() + pad)
        ax.plot(*leg.goal.pose[:2], "g*", ms=12, label=f"goal {leg.goal.id}")
        ax.set_aspect("equal")
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.legend(loc="best", fontsize=8)
        ax.set_title(f"run {leg.run}, leg {k}: to goal {leg.goal.id}")
        f = out_dir / f"leg{k:02d}_goal{leg.goal.id}_path.png"
        fig.savefig(f, dpi=110, bbox_inches="tight")
        plt.close(fig)
        files.append(f)
        if len(tr):
            fig, ax = plt.subplots(figsize=(9, 4))
            t = tr[:, 0] - tr[0, 0]
            ax.plot(t, tr[:, 4], label="vx (m/s)")
            ax.plot(t, tr[:, 5], label="vy (m/s)")
            ax.plot(t, tr[:, 6], label="wz (rad/s)")
            ax.set_xlabel("time (s)")
            ax.grid(True, alpha=0.3)
            ax.legend(loc="best", fontsize=8)
            ax.set_title(f"run {leg.run}, leg {k}: velocities to goal {leg.goal.id}")
            f = out_dir / f"leg{k:02d}_goal{leg.goal.id}_velocity.png"
            fig.savefig(f, dpi=110, bbox_inches="tight")
            plt.close(fig)
            files.append(f)
    return files


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("scenario", help="run navigation scenarios in the simulator")
    ssub = p.add_subparsers(dest="scenario_command", required=True, metavar="ACTION")
    rp = ssub.add_parser("run", help="run a scenario file and print the error table")
    rp.add_argument("file", help="scenario TOML")
    rp.add_argument("--json", help="write the per-run results to this file")
    rp.add_argument("--maps-dir", help="folder the scenario's map path is relative to when it is not next to the "
                    "file (default: $ZAGV_MAPS_DIR)")
    rp.add_argument("--plots", help="write per-leg path and velocity plots (PNG) into this folder")
    rp.add_argument("--goal-timeout", type=float, default=900.0, help="sim seconds per goal (default %(default)s)")
    rp.add_argument("--repeats", type=int, help="override the file's repeats")
    rp.add_argument("--speed", type=float, help="override the file's sim speed factor")
    rp.add_argument("--set", action="append", default=[], metavar="SERVICE.KEY=VALUE",
                    help="config override passed to the stack (zagv up --set)")
    rp.add_argument("--run-dir", help="folder for the stack's run state and log (default: temporary)")
    rp.add_argument("--start-seed", type=int, help="start the stack's services in a random order (zagv up)")
    rp.add_argument("--start-delay-max", type=float, default=0.0, metavar="S",
                    help="with --start-seed: random 0..S s delay before each service (zagv up)")
    rp.add_argument("--mqtt-broker", metavar="HOST:PORT",
                    help="[vda5050] scenarios: the MQTT broker of the robots and the master (default: embedded)")
    rp.set_defaults(func=run)
    from services.cli.scenario_generate import add_parser as add_generate

    add_generate(ssub)
    from services.cli.scenario_suite import add_parser as add_suite

    add_suite(ssub)


def run(args: argparse.Namespace) -> int:
    from services.cli.stack_process import Stack

    try:
        sc = load_scenario(args.file, args.maps_dir)
    except ScenarioError as exc:
        print(f"zagv scenario: {exc}", file=sys.stderr)
        return 2
    if args.repeats:
        sc.repeats = args.repeats
    if args.speed:
        sc.speed = args.speed
    if sc.vda5050 is not None:
        from services.cli.scenario_vda5050 import run_vda5050_fleet

        return run_vda5050_fleet(sc, args)
    if sc.robots:
        from services.cli.scenario_fleet import run_fleet

        return run_fleet(sc, args)
    run_dir = Path(args.run_dir or tempfile.mkdtemp(prefix="zagv-scenario-"))
    run_dir.mkdir(parents=True, exist_ok=True)
    extra = ["--headless"]
    if sc.mapping is not None:  # SLAM's map frame starts where the simulated robot starts: at the scenario's start
        x, y, th = sc.start
        extra += ["--mapping", "--set", f"sim.start_pose=[{x!r}, {y!r}, {th!r}]",
                  "--set", f"localization.initial_pose_x={x!r}", "--set", f"localization.initial_pose_y={y!r}",
                  "--set", f"localization.initial_pose_yaw={th!r}"]
    extra += [a for s in args.set for a in ("--set", s)]
    if args.start_seed is not None:
        extra += ["--start-seed", str(args.start_seed), "--start-delay-max", str(args.start_delay_max)]
    stack = Stack(run_dir, None, world=sc.world or "corridor", map_yaml=sc.map_yaml, speed=sc.speed,
                  extra_args=extra)
    print(f"zagv scenario: starting the simulated stack (log {run_dir / 'stack.log'})", flush=True)
    try:
        stack.start(ready_timeout_s=120.0)
        session = stack.session()

        truth_yaml = sc.map_yaml or str(run_dir / "world.yaml")  # zagv up renders the world there

        async def main() -> tuple[list[dict], list[Leg], int, list[bool], Any, m.OccupancyGrid | None]:
            runs, legs, collisions, detours, mapping = await run_scenario(
                sc, session, stack.keys, goal_timeout_s=args.goal_timeout, plots=bool(args.plots),
                progress=lambda s: print(s, flush=True), truth_yaml=truth_yaml)
            grid = None
            if args.plots:
                with contextlib.suppress(QueryError):
                    grid = await query(session, stack.keys, "map", m.Empty(), timeout_s=5.0)
            return runs, legs, collisions, detours, mapping, grid

        runs, legs, collisions, detours, mapping, grid = asyncio.run(main())
    except (AssertionError, RuntimeError, QueryError) as exc:
        print(f"zagv scenario: {exc}", file=sys.stderr)
        return 1
    finally:
        stack.stop()
    summary = summarize(runs)
    if mapping is not None:
        print(mapping.line())
    print(format_table(summary))
    total = sum(r["total"] for r in summary)
    reached = sum(r["reached"] for r in summary)
    tot = leg_totals(runs)
    print(f"reached {reached}/{total} goals within tolerance (ground truth); nav claimed {tot['claimed']}, "
          f"{tot['claimed_outside']} of them outside the tolerance; collisions: {collisions}; recoveries: "
          f"{tot['recoveries']}; localization error max {tot['loc_error_max_m']:.3f} m, RMS "
          f"{tot['loc_error_rms_m']:.3f} m; {tot['time_per_metre_s']:.1f} s per metre driven")
    if detours:
        print(f"replanned around the dynamic obstacle in {sum(detours)}/{len(detours)} legs")
    if args.json:
        result: dict[str, Any] = {"runs": runs}
        if mapping is not None:
            result["mapping"] = mapping.to_json()
        Path(args.json).write_text(json.dumps(result, indent=2))
    if args.plots:
        files = draw_plots(legs, grid, Path(args.plots))
        print(f"plots: {len(files)} files in {args.plots}")
    return 0 if reached == total and collisions == 0 else 1
