"""``zagv map bench FOLDER``: build and evaluate a map from every laser log in a folder, one table row per log.

Logs are the ``.clf``, ``.bag`` and ``.log.gz`` files under FOLDER (recursively). Per log and odometry setting:
- a log with a relations file next to it (``NAME.relations`` for ``NAME.clf`` / ``NAME.orig.bag`` / ``NAME.bag``):
  the Kümmerle et al. 2009 relative-pose error (translational mean, m; rotational mean, rad) on the laser poses;
- a log whose name contains ``corrected`` holds a reference trajectory, not odometry: SLAM gets that trajectory
  corrupted by ``OdometryNoise.for_reference`` (``--odometry clean``) or ``OdometryNoise.degraded``, or unchanged
  (``--odometry exact``: what the scan matching and the back end make of perfect odometry, i.e. the part of the error
  that odometry cannot be blamed for), and the row gives the RMS position error after rigid alignment (``ate_rms_m``)
  against the reference, with the Sim(2) fit (``evaluation.aligned_trajectory_error``): ``reference_scale``, how
  much larger the reference is than the map, and ``ate_scaled_rms_m``, the error left after that fit;
- the real-time factor (log duration ÷ wall time of SLAM; ``-`` when the log's stamps are unusable) and by CPU time;
- loop closures accepted / rejected, and ``false``: accepted closures whose measurement disagrees with a reference
  (the corrected trajectory, or for a relations log under degraded odometry the same log's clean-odometry result)
  by more than 0.3 m or 0.05 rad, and of those ``unjudged``: the ones with an end at a reference pose that its own
  scans disagree with (``reference_check.suspect_reference_poses``: a corrected log's poses are a SLAM result with
  errors of their own, so such a closure may be right and the reference wrong there);
- against the same reference, the front end's own bias (``evaluation.edge_bias`` on the keyframe edges as they
  entered the graph: loop closures move the poses, not these measurements): ``edge_along_pct``, how much longer (+)
  or shorter (−) the edges are along the direction of travel, ``edge_heading_deg_per_100m``, their summed heading
  error per 100 m, and ``edge_turn_pct``, how much smaller (−) or larger (+) than the reference's their turns are.
  A map uniformly smaller than its reference (``ref_scale`` > 1) with edges short by the same fraction is a matter
  of metric, not of bending.
``--odometry degraded`` corrupts the odometry with ``OdometryNoise.degraded(seed)`` (wheel scale ±5 %, heading drift
2°/m, jumps; see ``services/localization/slam/odometry_noise.py``), ``--odometry turning`` with
``OdometryNoise.turning(seed)`` (the same, and turns scaled ±8 % with white noise growing with each turn, which the
degraded setting leaves out: a robot turning on the spot keeps its heading there); ``both`` runs clean then degraded,
``all`` clean, degraded and turning. ``--max-scans`` caps every log (a quick slice), ``--only`` keeps logs whose
name contains one of the given words, ``--json`` writes the rows, ``--set KEY=VALUE`` (repeatable) overrides a
``SlamConfig`` field.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import sys
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TextIO

import numpy as np

LOG_SUFFIXES = (".clf", ".bag", ".log.gz", ".clf.gz")


@dataclass
class BenchResult:
    log: str
    odometry: str
    scans: int
    keyframes: int
    translation_error_m: float | None
    rotation_error_rad: float | None
    ate_rms_m: float | None
    ate_scaled_rms_m: float | None
    reference_scale: float | None
    realtime_factor: float | None
    realtime_factor_cpu: float | None
    ms_per_scan: float
    closures_accepted: int
    closures_rejected: int
    closures_false: int | None
    closures_unjudged: int | None
    fallback_matches: int
    edge_along_pct: float | None
    edge_heading_deg_per_100m: float | None
    edge_turn_pct: float | None
    odometry_noise: str


def find_logs(folder: Path) -> list[Path]:
    """The logs under ``folder``: CARMEN and ROS 1 files by suffix, and ROS 2 bags as their folders (the folder of
    each ``metadata.yaml``; the storage files inside are not logs of their own)."""
    ros2_bags = {p.parent for p in folder.rglob("metadata.yaml")}
    files = {p for p in folder.rglob("*") if p.is_file() and p.name.endswith(LOG_SUFFIXES)
             and not ros2_bags.intersection(p.parents)}
    return sorted(files | ros2_bags)


def relations_for(log_path: Path) -> Path | None:
    """``NAME.relations`` next to the log ``NAME.orig.bag``, ``NAME.bag``, ``NAME.clf[.gz]`` or ROS 2 bag folder
    ``NAME``."""
    name = log_path.name
    if log_path.is_dir():
        candidate = log_path.with_name(name + ".relations")
        return candidate if candidate.is_file() else None
    for suffix in (".orig.bag", ".bag", ".clf.gz", ".clf"):
        if name.endswith(suffix):
            candidate = log_path.with_name(name[: -len(suffix)] + ".relations")
            return candidate if candidate.is_file() else None
    return None


def has_reference(log_path: Path) -> bool:
    return "corrected" in log_path.name


def parse_overrides(items: list[str] | None):
    """``SlamConfig`` with ``KEY=VALUE`` overrides (values parsed as JSON, else kept as strings; the config's
    types are checked), or None for the defaults."""
    import msgspec

    from services.localization.slam.mapper import SlamConfig

    if not items:
        return None
    fields: dict[str, object] = {}
    for item in items:
        key, sep, text = item.partition("=")
        if not sep or not key:
            raise ValueError(f"--set expects KEY=VALUE (got {item!r})")
        try:
            fields[key] = json.loads(text)
        except json.JSONDecodeError:
            fields[key] = text
    merged = {**msgspec.structs.asdict(SlamConfig()), **fields}
    try:
        return msgspec.convert(merged, SlamConfig, strict=False)
    except msgspec.ValidationError as exc:
        raise ValueError(f"--set: {exc}") from exc


def bench_log(log_path: Path, odometry: str, *, seed: int = 1, max_scans: int | None = None,
              reference: np.ndarray | None = None, log=None, config=None):
    """One row for ``log_path`` with ``odometry`` 'clean', 'degraded' or 'exact' (``config``: a ``SlamConfig``, None for
    the defaults); also returns the laser trajectory (for use as the degraded run's closure reference)."""
    from services.localization.slam.evaluation import (
        aligned_trajectory_error,
        edge_bias,
        false_closures,
        parse_relations,
        relative_pose_error,
        scan_poses,
    )
    from services.localization.slam.logs import read_log
    from services.localization.slam.odometry_noise import OdometryNoise, corrupt_odometry
    from services.localization.slam.offline import run_slam, scan_points
    from services.localization.slam.reference_check import suspect_reference_poses

    log = log or read_log(log_path)
    if max_scans is not None:
        log.scans = log.scans[:max_scans]
    truth_scans = None
    if has_reference(log_path):
        truth_scans = scan_poses(np.array([s.odom_pose for s in log.scans]), log.sensor_pose)
        reference = truth_scans
    noise = None
    if odometry == "degraded":
        noise = OdometryNoise.degraded(seed)
    elif odometry == "turning":
        noise = OdometryNoise.turning(seed)
    elif truth_scans is not None and odometry != "exact":
        noise = OdometryNoise.for_reference(seed)
    if noise is not None:
        log, _ = corrupt_odometry(log, noise)
    run = run_slam(log, config)
    slam = run.slam
    stamps, poses = slam.trajectory()
    laser = scan_poses(poses, log.sensor_pose)
    trans = rot = ate = ate_scaled = scale = None
    relations_path = relations_for(log_path)
    if relations_path is not None:
        with relations_path.open() as f:
            error = relative_pose_error(stamps, laser, parse_relations(f))
        trans, rot = error.translation_mean_m, error.rotation_mean_rad
    if truth_scans is not None:
        fit = aligned_trajectory_error(laser, truth_scans)
        ate, ate_scaled, scale = fit.rms_m, fit.scaled_rms_m, fit.scale
    accepted = slam.loop_closures
    n_false = n_unjudged = None
    bias = None
    if reference is not None and len(reference) == len(laser):
        kf_scan = slam.keyframe_scan_indices()
        mount = np.broadcast_to(log.sensor_pose, (len(reference), 3))
        from services.common.se2 import compose, inverse

        robot_reference = compose(reference, inverse(mount))
        from_scans, to_scans = kf_scan[[c.from_ for c in accepted]], kf_scan[[c.to for c in accepted]]
        flagged = false_closures(from_scans, to_scans, np.array([c.measurement for c in accepted]).reshape(-1, 3),
                                 robot_reference)
        n_false = int(flagged.sum())
        suspect = suspect_reference_poses(lambda i: scan_points(log, i), robot_reference,
                                          np.concatenate([from_scans[flagged], to_scans[flagged]]))
        n_unjudged = sum(1 for j, k in zip(from_scans[flagged], to_scans[flagged], strict=True)
                         if int(j) in suspect or int(k) in suspect)
        ks, steps = slam.sequential_edges()
        with contextlib.suppress(ValueError):  # no edge (long enough) to have a direction: one keyframe, spot turns
            bias = edge_bias(robot_reference[kf_scan[ks - 1]], robot_reference[kf_scan[ks]], steps)
    row = BenchResult(
        log=log_path.name, odometry=odometry, scans=run.n_scans, keyframes=slam.n_keyframes,
        translation_error_m=trans, rotation_error_rad=rot, ate_rms_m=ate, ate_scaled_rms_m=ate_scaled,
        reference_scale=scale,
        realtime_factor=run.realtime_factor if log.stamps_from_log else None,
        realtime_factor_cpu=run.realtime_factor_cpu if log.stamps_from_log else None,
        ms_per_scan=1e3 * run.processing_s / max(run.n_scans, 1),
        closures_accepted=len(accepted), closures_rejected=len(slam.rejected_closures), closures_false=n_false,
        closures_unjudged=n_unjudged,
        fallback_matches=slam.fallback_matches, odometry_noise=noise.describe() if noise else "as logged",
        edge_along_pct=None if bias is None else bias.along_pct,
        edge_heading_deg_per_100m=None if bias is None else bias.heading_deg_per_100m,
        edge_turn_pct=None if bias is None or math.isnan(bias.turn_pct) else bias.turn_pct)
    return row, laser


def _fmt(value, spec: str) -> str:
    return "-" if value is None else format(value, spec)


def print_table(rows: list[BenchResult], out: TextIO | None = None) -> None:
    """One row per log; ``out`` defaults to the current ``sys.stdout`` (looked up at call time)."""
    out = sys.stdout if out is None else out
    header = (f"{'log':34s} {'odometry':8s} {'scans':>6s} {'trans_m':>8s} {'rot_rad':>8s} {'ate_m':>7s} "
              f"{'ate_sim2':>8s} {'ref_scale':>9s} {'rtf':>6s} {'rtf_cpu':>7s} {'ms/scan':>7s} {'loops':>5s} "
              f"{'rej':>4s} {'false':>5s} {'unjdg':>5s} {'fallbk':>6s} {'edge_%':>7s} {'deg/100m':>8s} {'turn_%':>7s}")
    print(header, file=out)
    for r in rows:
        print(f"{r.log:34s} {r.odometry:8s} {r.scans:6d} {_fmt(r.translation_error_m, '8.4f')} "
              f"{_fmt(r.rotation_error_rad, '8.4f')} {_fmt(r.ate_rms_m, '7.3f')} {_fmt(r.ate_scaled_rms_m, '8.3f')} "
              f"{_fmt(r.reference_scale, '9.5f')} {_fmt(r.realtime_factor, '6.1f')} "
              f"{_fmt(r.realtime_factor_cpu, '7.1f')} {r.ms_per_scan:7.1f} {r.closures_accepted:5d} "
              f"{r.closures_rejected:4d} {_fmt(r.closures_false, '5d')} {_fmt(r.closures_unjudged, '5d')} "
              f"{r.fallback_matches:6d} "
              f"{_fmt(r.edge_along_pct, '+7.3f')} {_fmt(r.edge_heading_deg_per_100m, '+8.2f')} "
              f"{_fmt(r.edge_turn_pct, '+7.2f')}", file=out)


def run_bench(args: argparse.Namespace) -> int:
    folder = Path(args.folder)
    if not folder.is_dir():
        print(f"zagv map bench: {folder} is not a folder", file=sys.stderr)
        return 2
    logs = find_logs(folder)
    if args.only:
        logs = [p for p in logs if any(word in p.name for word in args.only)]
    if not logs:
        print(f"zagv map bench: no .clf, .bag, .log.gz log or ROS 2 bag folder in {folder}", file=sys.stderr)
        return 2
    try:
        config = parse_overrides(args.set)
    except ValueError as exc:
        print(f"zagv map bench: {exc}", file=sys.stderr)
        return 2
    settings = {"both": ["clean", "degraded"], "all": ["clean", "degraded", "turning"]}.get(args.odometry,
                                                                                          [args.odometry])
    rows: list[BenchResult] = []
    for path in logs:
        clean_laser = None
        for setting in settings:
            reference: np.ndarray | None = clean_laser if setting in ("degraded", "turning") else None
            try:
                row, laser = bench_log(path, setting, seed=args.seed, max_scans=args.max_scans, reference=reference,
                                        config=config)
            except (OSError, ValueError) as exc:
                print(f"zagv map bench: {path.name}: {exc}", file=sys.stderr)
                continue
            if setting == "clean":
                clean_laser = laser
            rows.append(row)
            print_table([row], out=sys.stderr)
    print_table(rows)
    if args.json:
        Path(args.json).write_text(json.dumps([asdict(r) for r in rows], indent=2))
    return 0


def add_bench_parser(map_subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = map_subparsers.add_parser("bench", help="build + evaluate a map from every log in a folder (table)")
    p.add_argument("folder", help="folder searched recursively for .clf, .bag and .log.gz logs")
    p.add_argument("--odometry", choices=["clean", "degraded", "turning", "both", "all", "exact"], default="clean",
                   help="odometry as logged (reference logs: lightly corrupted), degraded, turning (degraded with "
                        "rotation errors too), both (clean, degraded), all (clean, degraded, turning), or for "
                        "reference logs exact (the reference itself; default: clean)")
    p.add_argument("--seed", type=int, default=1, help="seed of the odometry corruption (default 1)")
    p.add_argument("--only", nargs="+", metavar="WORD", help="only logs whose file name contains one of these")
    p.add_argument("--max-scans", type=int, help="process only the first N scans of each log")
    p.add_argument("--json", help="also write the rows to this JSON file")
    p.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="override a SlamConfig field (repeatable; VALUE parsed as JSON), e.g. --set levels=4")
    p.set_defaults(func=run_bench)
    return p


def run_localize(args: argparse.Namespace) -> int:
    """AMCL on the real scans of every corrected log against the map of its reference trajectory."""
    from services.localization.slam.localization_check import localize_on_reference
    from services.localization.slam.logs import read_log
    from services.localization.slam.odometry_noise import OdometryNoise

    folder = Path(args.folder)
    logs = [p for p in find_logs(folder) if has_reference(p)] if folder.is_dir() else []
    if args.only:
        logs = [p for p in logs if any(word in p.name for word in args.only)]
    if not logs:
        print(f"zagv map localize: no corrected (reference-trajectory) log in {folder}", file=sys.stderr)
        return 2
    noise = OdometryNoise.for_reference(args.seed)
    print(f"odometry: reference corrupted with {noise.describe()}")
    print(f"{'log':34s} {'scans':>6s} {'updates':>7s} {'mean_m':>7s} {'rms_m':>7s} {'max_m':>7s} {'rot_rms':>7s} "
          f"{'lost':>5s}")
    results = {}
    for path in logs:
        log = read_log(path)
        if args.max_scans:
            log.scans = log.scans[:args.max_scans]
        try:
            error = localize_on_reference(log, noise)
        except ValueError as exc:
            print(f"zagv map localize: {path.name}: {exc}", file=sys.stderr)
            continue
        results[path.name] = error.as_dict()
        print(f"{path.name:34s} {len(log.scans):6d} {error.n_updates:7d} {error.mean_m:7.3f} {error.rms_m:7.3f} "
              f"{error.max_m:7.3f} {error.rotation_rms_rad:7.4f} {100 * error.lost_fraction:4.0f}%", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2))
    return 0


def add_localize_parser(map_subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = map_subparsers.add_parser("localize", help="AMCL on corrected logs' real scans against their reference map")
    p.add_argument("folder", help="folder searched recursively for *corrected* CARMEN logs")
    p.add_argument("--seed", type=int, default=1, help="seed of the odometry corruption and the filter")
    p.add_argument("--only", nargs="+", metavar="WORD", help="only logs whose file name contains one of these")
    p.add_argument("--max-scans", type=int, help="use only the first N scans of each log")
    p.add_argument("--json", help="also write the figures to this JSON file")
    p.set_defaults(func=run_localize)
    return p
