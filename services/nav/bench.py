"""Nav benchmarks: inflation of a 1000x1000 costmap, A* corner to corner, one DWA cycle (20x5x20 samples).

A* rows (workloads in services/nav/workloads.py, docs/performance.md):

- ``astar.plan_ms``: the compiled planner on the documented 1000 x 1000 warehouse workload (median of 2 x 7 plans);
- ``astar.c_reference_ms`` / ``astar.vs_c_reference``: the C -O2 reference A* of the development data's harness
  (``$ZAGV_SHARED/reference/harness/astar.c``, default ``shared`` next to the repository), built with gcc and run on
  the same workload in the same run, interleaved with ours; left out, saying so, where the harness or gcc is absent;
- ``astar.python_ms``: the pure-Python reference loop on the same workload (one plan);
- ``astar.<map>_ms`` / ``astar.<map>_python_ms``: the largest ROS map of ``$ZAGV_SHARED/data/maps``, corner to
  corner, compiled and pure Python (left out, saying so, without the data);
- ``astar.rects_1000_ms``: the random-rectangles 1000 x 1000 map of the costmap row;
- ``astar.import_ms``: start-up cost, importing the planner with its compiled loop in a fresh interpreter.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from services.common.bench import BenchRow, time_calls
from services.common.devdata import shared_dir
from services.common.robot import TwistLimits
from services.nav.astar import AStarPlanner
from services.nav.costmap import Costmap2D, Footprint, GlobalCostmap, InflationLayer, ObstacleLayer, StaticLayer
from services.nav.dwa import DwaConfig, DwaPlanner
from services.nav.workloads import Workload, real_map_workload, warehouse_costmap

RESOLUTION = 0.05
REPO_ROOT = Path(__file__).resolve().parents[2]


def obstacle_map(n: int = 1000, seed: int = 7) -> np.ndarray:
    """An n x n occupancy grid (int8) with ~80 random rectangular obstacles and free corners."""
    rng = np.random.default_rng(seed)
    occ = np.zeros((n, n), dtype=np.int8)
    for _ in range(80):
        i, j = rng.integers(0, n, 2)
        occ[i:i + rng.integers(5, 60), j:j + rng.integers(5, 60)] = 100
    occ[:40, :40] = 0
    occ[-40:, -40:] = 0
    return occ


def inflated_costmap(n: int = 1000) -> GlobalCostmap:
    cm = GlobalCostmap(Costmap2D.empty(1, 1, RESOLUTION), StaticLayer(), ObstacleLayer(),
                       InflationLayer(0.63, 0.645, 10.0), Footprint(0.63))
    cm.set_map(obstacle_map(n), RESOLUTION, 0.0, 0.0)
    return cm


def bench_costmap() -> list[BenchRow]:
    cm = inflated_costmap()
    t = time_calls(lambda: cm.inflation.update(cm.master), repeat=10, warmup=1)
    return [BenchRow("costmap.inflate_ms", float(np.median(t) * 1e3), "ms", "1000x1000 cells, r = 0.645 m")]


def _plan_ms(planner: AStarPlanner, wl: Workload, repeat: int) -> np.ndarray:
    return time_calls(lambda: planner.plan(wl.cost, wl.start, wl.goal, wl.resolution), repeat=repeat, warmup=0,
                      max_s=60.0) * 1e3



def _field(pattern: str, text: str) -> str:
    """The first group of ``pattern`` (multi-line) in ``text``; ValueError naming the pattern when it is absent."""
    found = re.search(pattern, text, re.M)
    if found is None:
        raise ValueError(f"no line matching {pattern!r} in the C reference's output")
    return found.group(1)

class CReference:
    """The harness's C A* built in a temporary folder and fed the workload as ``costmap_1000.npy`` + ``meta.txt``."""

    def __init__(self, source: Path, wl: Workload) -> None:
        self.dir = Path(tempfile.mkdtemp(prefix="zagv-astar-ref-"))
        (self.dir / "out").mkdir()
        np.save(self.dir / "costmap_1000.npy", wl.cost)
        (self.dir / "meta.txt").write_text(
            f"costmap_resolution {wl.resolution!r}\nstart_row {wl.start[0]}\nstart_col {wl.start[1]}\n"
            f"goal_row {wl.goal[0]}\ngoal_col {wl.goal[1]}\n")
        self.exe = self.dir / "astar"
        subprocess.run(["gcc", "-O2", "-std=c11", "-o", str(self.exe), str(source), "-lm"], check=True,
                       capture_output=True)

    def run_ms(self, runs: int = 7) -> tuple[float, float]:
        """(median plan time in ms, path cost in cell units) of ``runs`` plans."""
        out = subprocess.run([str(self.exe), str(self.dir), str(runs)], check=True, capture_output=True,
                             text=True).stdout
        median = float(_field(r"^TIME astar c (\S+)", out))
        cost = float(_field(r"^cost (\S+)", (self.dir / "out" / "astar_c.txt").read_text()))
        return median, cost

    def close(self) -> None:
        shutil.rmtree(self.dir, ignore_errors=True)


def _largest_map(maps: Path) -> Path | None:
    from PIL import Image

    from services.common.map_io import read_map_yaml

    best, best_cells = None, 0
    for yaml_path in sorted(maps.glob("*/*.yaml")):
        image = yaml_path.parent / read_map_yaml(yaml_path)["image"]
        with Image.open(image) as im:
            cells = im.width * im.height
        if cells > best_cells:
            best, best_cells = yaml_path, cells
    return best


def bench_astar() -> list[BenchRow]:
    planner, python = AStarPlanner(), AStarPlanner(compiled=False)
    if not planner.uses_compiled:
        print("bench astar: the compiled search is not built; astar.plan_ms is the pure-Python loop", file=sys.stderr)
    wl = warehouse_costmap()
    first = planner.plan(wl.cost, wl.start, wl.goal, wl.resolution)
    if not first.ok:
        raise RuntimeError(f"warehouse workload has no path: {first.error}")
    cells = first.cost / wl.resolution
    source = shared_dir() / "reference" / "harness" / "astar.c"
    ref = None
    if source.is_file() and shutil.which("gcc"):
        ref = CReference(source, wl)
    else:
        print(f"bench astar: no C reference ({source} or gcc missing); astar.c_reference_ms left out", file=sys.stderr)
    ours: list[float] = []
    theirs: list[float] = []
    ref_cost: float | None = None
    try:
        for _ in range(2):  # interleaved, so both see the same machine load
            if ref is not None:
                median, ref_cost = ref.run_ms(7)
                theirs.append(median)
            ours.extend(_plan_ms(planner, wl, 7))
    finally:
        if ref is not None:
            ref.close()
    plan_ms = float(np.median(ours))
    rows = [BenchRow("astar.plan_ms", plan_ms, "ms",
                     f"<= 1.5x C -O2; {wl.name} (seed {wl.seed}), {first.expanded} expansions, cost {cells:.6f} cells")]
    if theirs and ref_cost is not None:
        c_ms = float(np.median(theirs))
        rows += [BenchRow("astar.c_reference_ms", c_ms, "ms",
                          f"C -O2 reference, same workload and run; cost {ref_cost:.6f} cells "
                          f"(ours differs by {abs(ref_cost - cells):.1e})"),
                 BenchRow("astar.vs_c_reference", plan_ms / c_ms, "x", "<= 1.5")]
    t_py = _plan_ms(python, wl, 1)
    rows.append(BenchRow("astar.python_ms", float(t_py[0]), "ms", "pure-Python reference loop, same workload"))

    maps = shared_dir() / "data" / "maps"
    largest = _largest_map(maps) if maps.is_dir() else None
    if largest is None:
        print(f"bench astar: no maps in {maps} (set ZAGV_SHARED); real-map rows left out", file=sys.stderr)
    else:
        real = real_map_workload(largest)
        res = planner.plan(real.cost, real.start, real.goal, real.resolution)
        h, w = real.cost.shape
        rows.append(BenchRow(f"astar.{real.name}_ms", float(np.median(_plan_ms(planner, real, 5))), "ms",
                             f"{w}x{h} at {real.resolution} m, corner to corner, {res.expanded} expansions, "
                             f"{res.cost:.1f} m-equivalent" if res.ok else res.error))
        rows.append(BenchRow(f"astar.{real.name}_python_ms", float(_plan_ms(python, real, 1)[0]), "ms",
                             "pure-Python reference loop"))

    cm = inflated_costmap()
    n = cm.master.width
    rects = Workload("rects", cm.master.cost, (20, 20), (n - 21, n - 21), RESOLUTION)
    res = planner.plan(rects.cost, rects.start, rects.goal, RESOLUTION)
    rows.append(BenchRow("astar.rects_1000_ms", float(np.median(_plan_ms(planner, rects, 5))), "ms",
                         f"random rectangles 1000x1000, {res.expanded} expansions"))
    code = "import time; t = time.perf_counter(); import services.nav._astar; print((time.perf_counter() - t) * 1e3)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO_ROOT)
    if out.returncode == 0 and planner.uses_compiled:
        import services.nav._astar as _astar

        so = Path(_astar.__file__)
        rows.append(BenchRow("astar.import_ms", float(out.stdout), "ms",
                             f"start-up cost of the compiled loop (fresh interpreter); {so.stat().st_size} B on disk"))
    return rows


def bench_dwa() -> list[BenchRow]:
    cm = inflated_costmap(100)
    cfg = DwaConfig(vx_samples=20, vy_samples=5, wz_samples=20, sim_time_s=1.7)
    dwa = DwaPlanner(cfg, TwistLimits(), Footprint(0.63))
    path = np.column_stack([np.linspace(1.0, 4.0, 61), np.full(61, 1.0), np.zeros(61)])
    pose = (1.0, 1.0, 0.0)
    res = dwa.plan(cm.master, pose, (0.1, 0.0, 0.0), path, (4.0, 1.0, 0.0), previous=(0.1, 0.0, 0.0))
    n = len(dwa.samples((0.1, 0.0, 0.0)))
    t = time_calls(lambda: dwa.plan(cm.master, pose, (0.1, 0.0, 0.0), path, (4.0, 1.0, 0.0),
                                    previous=(0.1, 0.0, 0.0)), repeat=50, warmup=3)
    return [BenchRow("dwa.cycle_ms", float(np.median(t) * 1e3), "ms",
                     f"<= 10 ms; {n} samples x {cfg.sim_steps} steps, {res.valid_samples} valid")]


BENCHES = [("costmap", bench_costmap), ("dwa", bench_dwa), ("astar", bench_astar)]
