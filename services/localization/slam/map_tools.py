"""Offline SLAM commands of ``zagv map``: ``build`` a map from a laser log and ``eval`` its accuracy.

``zagv map build LOG --out DIR`` runs graph SLAM over a CARMEN ``.clf`` or ROS 1 ``.bag`` log and writes
``DIR/NAME.yaml`` + ``DIR/NAME.pgm`` (ROS map_server, trinary) and ``DIR/NAME.trajectory.txt``
(``stamp_s x_m y_m theta_rad`` per scan). ``zagv map eval LOG RELATIONS [--trajectory FILE] [--json OUT]``
reports the Kümmerle et al. 2009 relative-pose error of that trajectory (estimated anew unless given), on the
laser poses (the robot poses composed with the log's laser mount) since the relations relate scans.
``python -m services.localization.slam`` (which ``zagv map`` runs) calls ``add_build_parser`` and ``add_eval_parser``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import msgspec


def _slam_config(settings: list[str]):
    from services.localization.slam.mapper import SlamConfig

    values = {}
    for item in settings:
        key, sep, text = item.partition("=")
        if not sep:
            raise SystemExit(f"--set expects key=value, got {item!r}")
        try:
            values[key.strip()] = json.loads(text)
        except json.JSONDecodeError:
            values[key.strip()] = text
    try:
        return msgspec.convert(values, SlamConfig)
    except msgspec.ValidationError as exc:
        raise SystemExit(f"bad SLAM setting: {exc}") from exc


def _add_common(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--set", dest="settings", action="append", default=[], metavar="KEY=VALUE",
                        help="SLAM tuning (a SlamConfig field, e.g. --set resolution_m=0.05)")
    parser.add_argument("--max-scans", type=int, help="process only the first N scans")


def add_build_parser(map_subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = map_subparsers.add_parser("build", help="build a map (YAML+PGM) and trajectory from a .clf or .bag log")
    p.add_argument("log", help="CARMEN .clf or ROS 1 .bag file with laser scans and odometry")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--name", default="map", help="base name of the files written (default: map)")
    p.add_argument("--resolution", type=float, help="map cell size in m (default: the SLAM resolution)")
    _add_common(p)
    p.set_defaults(func=run_build)
    return p


def add_eval_parser(map_subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = map_subparsers.add_parser("eval", help="relative-pose error (Kümmerle 2009) against ground-truth relations")
    p.add_argument("log", help="the log the trajectory comes from (.clf or .bag)")
    p.add_argument("relations", help="relations file: 't1 t2 dx dy dz roll pitch yaw' per line")
    p.add_argument("--trajectory", help="evaluate this trajectory file instead of running SLAM on LOG")
    p.add_argument("--json", help="also write the figures to this JSON file")
    p.add_argument("--robot-frame", action="store_true",
                   help="compare robot poses, not laser poses (the relations relate scans, i.e. laser poses)")
    _add_common(p)
    p.set_defaults(func=run_eval)
    return p


def _read(path: str):
    from services.localization.slam.logs import read_log

    try:
        log = read_log(path)
    except (OSError, ValueError) as exc:
        raise SystemExit(f"zagv map: cannot read {path}: {exc}") from exc
    if not log.scans:
        raise SystemExit(f"zagv map: {path} holds no laser scan")
    return log


def _run(args: argparse.Namespace, log=None):
    from services.localization.slam.offline import run_slam

    config = _slam_config(args.settings)
    log = log or _read(args.log)
    run = run_slam(log, config, max_scans=args.max_scans)
    slam = run.slam
    print(f"slam: {run.n_scans} scans, {slam.n_keyframes} keyframes, {len(slam.loop_closures)} loop closures "
          f"accepted, {len(slam.rejected_closures)} rejected, {slam.fallback_matches} scans placed by odometry "
          f"(match-quality gate), "
          f"{run.processing_s:.1f} s for {run.log_duration_s:.1f} s of log (x{run.realtime_factor:.1f} real time, "
          f"x{run.realtime_factor_cpu:.1f} by CPU time)",
          file=sys.stderr)
    return run


def run_build(args: argparse.Namespace) -> int:
    from services.localization.slam.map_files import write_ros_map, write_trajectory

    run = _run(args)
    out = Path(args.out)
    grid = run.slam.render_map(args.resolution)
    yaml_path = write_ros_map(grid, out, args.name)
    stamps, poses = run.slam.trajectory()
    write_trajectory(out / f"{args.name}.trajectory.txt", stamps, poses)
    print(f"wrote {yaml_path} ({grid.log_odds.shape[1]}x{grid.log_odds.shape[0]} cells at {grid.resolution_m} m) "
          f"and {out / (args.name + '.trajectory.txt')}")
    return 0


def run_eval(args: argparse.Namespace) -> int:
    from services.localization.slam.evaluation import parse_relations, relative_pose_error, scan_poses
    from services.localization.slam.map_files import read_trajectory

    try:
        with open(args.relations) as f:
            relations = parse_relations(f)
    except (OSError, ValueError) as exc:
        raise SystemExit(f"zagv map eval: cannot read relations {args.relations}: {exc}") from exc
    extra: dict = {}
    log = _read(args.log)
    if args.trajectory:
        stamps, poses = read_trajectory(args.trajectory)
    else:
        run = _run(args, log)
        stamps, poses = run.slam.trajectory()
        extra = {"processing_s": run.processing_s, "log_duration_s": run.log_duration_s,
                 "realtime_factor": run.realtime_factor,
                 "processing_cpu_s": run.processing_cpu_s, "keyframes": run.slam.n_keyframes,
                 "loop_closures": len(run.slam.loop_closures),
                 "loop_closures_rejected": len(run.slam.rejected_closures),
                 "odometry_fallbacks": run.slam.fallback_matches}
    if not args.robot_frame:
        poses = scan_poses(poses, log.sensor_pose)
    try:
        error = relative_pose_error(stamps, poses, relations)
    except ValueError as exc:
        raise SystemExit(f"zagv map eval: {exc}") from exc
    print(f"translational error {error.translation_mean_m:.4f} ± {error.translation_std_m:.4f} m "
          f"(max {error.translation_max_m:.3f} m), rotational error {error.rotation_mean_rad:.4f} ± "
          f"{error.rotation_std_rad:.4f} rad over {error.n_relations} relations"
          + (f" ({error.n_missing} without a matching scan)" if error.n_missing else ""))
    if args.json:
        Path(args.json).write_text(json.dumps({**error.as_dict(), **extra}, indent=2))
    return 0
