"""AMCL benchmarks: one sensor update plus resampling on a synthetic corridor map (no files needed)."""

from __future__ import annotations

import math
import sys
import time

import numpy as np

from services.common.bench import BenchRow
from services.common.map_io import OccupancyMap
from services.localization.amcl import AmclParams, ParticleFilter, beam_indices
from services.localization.uncertainty import PoseUncertainty, scan_information


def cpu_time_calls(fn, *, repeat: int, warmup: int = 5, max_s: float = 10.0) -> np.ndarray:
    """Thread CPU seconds of each call (robust to other processes sharing the cores; the work is single-threaded)."""
    for _ in range(warmup):
        fn()
    out = []
    start = time.perf_counter()
    for _ in range(repeat):
        t0 = time.thread_time()
        fn()
        out.append(time.thread_time() - t0)
        if time.perf_counter() - start > max_s:
            break
    return np.asarray(out)


def bench_map() -> OccupancyMap:
    """A 40 m x 20 m map (0.05 m cells): outer walls, a corridor and a few boxes."""
    res = 0.05
    data = np.zeros((400, 800), dtype=np.int8)
    data[:2, :] = data[-2:, :] = data[:, :2] = data[:, -2:] = 100
    data[180:184, 100:700] = 100
    for i in range(6):
        data[60 + 40 * (i % 3): 80 + 40 * (i % 3), 120 + 100 * i: 140 + 100 * i] = 100
    return OccupancyMap(data, res, (-5.0, -5.0, 0.0))


def update_ms(particles: int, beams: int = 60, repeat: int = 200) -> float:
    """Median CPU ms of sensor_update + resample with ``particles`` kept (min = max) and ``beams`` beams.

    Recovery injection is off: its sensor-resetting draw is a separate, occasional cost (``amcl.recovery_ms``).
    """
    params = AmclParams(min_particles=particles, max_particles=particles, max_beams=beams, random_seed=1,
                        recovery_alpha_slow=0.0, recovery_alpha_fast=0.0)
    pf = ParticleFilter(bench_map(), params)
    pf.init_gaussian((10.0, 3.0, 0.3), np.diag([0.5, 0.5, 0.3]))
    idx = beam_indices(541, beams)
    bearings = -math.radians(135) + idx * math.radians(0.5)
    ranges = np.random.default_rng(2).uniform(0.5, 15.0, size=idx.size)

    def one() -> None:
        pf.sensor_update(ranges, bearings, (0.45, 0.0, 0.0), 20.0)
        pf.resample()

    return float(np.median(cpu_time_calls(one, repeat=repeat, warmup=10, max_s=5.0)) * 1e3)


def recovery_ms() -> float:
    """Median ms of drawing 10% recovery particles by sensor resetting (20000 candidates weighed by the scan)."""
    params = AmclParams(random_seed=1)
    pf = ParticleFilter(bench_map(), params)
    idx = beam_indices(541, params.max_beams)
    bearings = -math.radians(135) + idx * math.radians(0.5)
    ranges = np.random.default_rng(2).uniform(0.5, 15.0, size=idx.size)
    pf.sensor_update(ranges, bearings, (0.45, 0.0, 0.0), 20.0)
    return float(np.median(cpu_time_calls(lambda: pf._recovery_poses(params.max_particles // 10), repeat=20,
                                          warmup=2, max_s=5.0)) * 1e3)


def corridor_rms() -> list[BenchRow]:
    """Tracking error along the Table 3 route of the corridor world (synthetic laser and odometry, core level)."""
    from services.common.world import World
    from services.localization.amcl import Amcl
    from services.localization.synthetic import TABLE3_ROUTE, drive, route

    world = World.load_builtin("corridor")
    amcl = Amcl(world.occupancy_map(), AmclParams(random_seed=1))
    amcl.set_initial_pose(TABLE3_ROUTE[0])
    result = drive(amcl, world, list(route(TABLE3_ROUTE)), seed=1)
    return [
        BenchRow("amcl.rms_error_m", result.rms_xy_m, "m", "<= 0.03 (corridor, Table 3 route, synthetic laser)"),
        BenchRow("amcl.rms_error_rad", result.rms_theta_rad, "rad", "<= 0.02"),
    ]


def uncertainty_update_ms(beams: int = 60, repeat: int = 500) -> float:
    """Median CPU ms of one scan's information (``uncertainty.scan_information``, ``beams`` beams) plus the
    tracked covariance's motion and scan updates: the per-update cost the uncertainty adds to the filter."""
    params = AmclParams(random_seed=1)
    pf = ParticleFilter(bench_map(), params)
    idx = beam_indices(541, beams)
    bearings = -math.radians(135) + idx * math.radians(0.5)
    ranges = np.random.default_rng(2).uniform(0.5, 15.0, size=idx.size)
    distance = pf.field.exact_distance_m()
    grid = pf.grid
    tracker = PoseUncertainty()

    def one() -> None:
        tracker.predict(0.3, (0.1, 0.0, 0.01))
        tracker.update(scan_information(distance, grid.origin, grid.resolution, params.sigma_hit, (10.0, 3.0, 0.3),
                                        ranges, bearings, (0.45, 0.0, 0.0)))

    return float(np.median(cpu_time_calls(one, repeat=repeat, warmup=10, max_s=5.0)) * 1e3)


def run() -> list[BenchRow]:
    return [
        BenchRow("amcl.update_ms", update_ms(2000), "ms", "<= 3 (2000 particles x 61 beams, update + resample)"),
        BenchRow("amcl.update_ms_5000", update_ms(5000, repeat=100), "ms", "5000 particles x 61 beams"),
        BenchRow("amcl.recovery_ms", recovery_ms(), "ms", "only while injecting (w_fast < w_slow)"),
        BenchRow("localization.uncertainty_update_ms", uncertainty_update_ms(), "ms",
                 "per filter update, 61 beams (small next to amcl.update_ms)"),
        *corridor_rms(),
    ]


def run_mapping() -> list[BenchRow]:
    """Live mapping on the synthetic corridor (lobby and main corridor to x = 15 m, 25 Hz scans at 1 m/s)."""
    from services.localization.slam.live_synthetic import run_corridor

    r = run_corridor(render_every_scans=50)
    return [BenchRow("mapping.cpu_ms_per_processed_scan", 1e3 * r.cpu_s_per_processed_scan, "ms", "< 40 (25 Hz)"),
            BenchRow("mapping.cpu_ms_max_scan", 1e3 * r.cpu_s_max, "ms"),
            BenchRow("mapping.processed_fraction", r.mapper.processed / r.scans, "", "motion gates 0.1 m / 0.1 rad"),
            BenchRow("mapping.pose_rms_m", float(np.sqrt(np.mean(r.errors_m ** 2))), "m")]


#: real SLAM maps of the development data the lost-detection bench runs on: (row name, maps/<folder>/<yaml>, factor
#: the map's cell is coarsened by first; 2 turns a 0.05 m map into the 0.10 m cells a coarser mapper draws)
REAL_MAPS = [("mit_stata_basement", "mit_stata_basement/stata_basement.yaml", 1),
             ("upenn_levine", "upenn_levine/levine.yaml", 1), ("ipa_izs_campus", "ipa_izs_campus/map.yaml", 1),
             ("mit_stata_basement_10cm", "mit_stata_basement/stata_basement.yaml", 2)]


def run_lost(seeds: tuple[int, ...] = (1, 2)) -> list[BenchRow]:
    """Kidnapping and a 2 m corrupted initial pose on the real maps (realmap.kidnap_trial/initial_pose_trial):
    per map the worst time to the "lost" verdict, and the outcomes; ``localization.lost_detect_s`` is the worst
    over all maps."""
    from services.common.devdata import shared_dir
    from services.common.map_io import coarsen, load_map
    from services.localization.realmap import initial_pose_trial, kidnap_trial

    root = shared_dir() / "data" / "maps"
    rows: list[BenchRow] = []
    worst = 0.0
    for folder, rel, factor in REAL_MAPS:
        path = root / rel
        if not path.is_file():
            print(f"bench: localization.lost_* on {folder} skipped: {path} not found", file=sys.stderr)
            continue
        grid = coarsen(load_map(path), factor)
        kid = [kidnap_trial(grid, s, AmclParams(random_seed=s)) for s in seeds]
        ini = [initial_pose_trial(grid, s, AmclParams(random_seed=s)) for s in seeds]
        detect = [t.detect_s for t in kid]
        missed = sum(d is None for d in detect)
        slowest = max((d for d in detect if d is not None), default=math.inf)
        worst = max(worst, slowest if not missed else math.inf)
        rows += [
            BenchRow(f"localization.lost_detect_s.{folder}", slowest, "s",
                     f"<= 1 (kidnapping, {len(seeds)} runs, {missed} not detected)"),
            BenchRow(f"localization.kidnap_recovered.{folder}", sum(t.outcome == "recovered" for t in kid), "runs",
                     f"of {len(seeds)}; reports_lost {sum(t.outcome == 'reports_lost' for t in kid)}, "
                     f"tracking_wrong {sum(t.outcome == 'tracking_wrong' for t in kid)}"),
            BenchRow(f"localization.initial_2m_recovered.{folder}", sum(t.outcome == "recovered" for t in ini),
                     "runs", f"of {len(seeds)}; reports_lost {sum(t.outcome == 'reports_lost' for t in ini)}, "
                             f"tracking_wrong {sum(t.outcome == 'tracking_wrong' for t in ini)}"),
        ]
    if rows:
        rows.insert(0, BenchRow("localization.lost_detect_s", worst, "s", "<= 1 (worst over the real maps)"))
    return rows


BENCHES = [("amcl", run), ("mapping", run_mapping), ("localization", run_lost)]
