"""Runs of AMCL on real occupancy maps, for tests and benches: a grid laser, routes through free space, kidnapping.

The world is the map itself with unknown cells solid (as the simulator renders a map), so beams end on walls the
map draws and on the edges of regions it never saw. ``GridLaser`` sphere-traces every beam through the Euclidean
distance transform of that raster (each step jumps by the clearance, at least a quarter cell). ``random_route``
walks straight legs between random poses whose footprint clearance stays above ``clearance_m``. ``run`` feeds AMCL
one scan per route pose with drifting odometry and records the errors, the filter's verdict and how long a loss
took to be noticed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from services.common.map_io import FREE, OccupancyMap
from services.common.se2 import compose, wrap_angle
from services.localization.amcl import Amcl, AmclParams, select_beams
from services.localization.synthetic import MOUNT, Odometry, route

Pose = tuple[float, float, float]


def axis_aligned(grid: OccupancyMap) -> OccupancyMap:
    """The same grid with its origin yaw dropped (runs happen in the grid's own frame)."""
    return OccupancyMap(grid.data, grid.resolution, (grid.origin[0], grid.origin[1], 0.0))


class GridLaser:
    """LMS111-like scans (270 deg, 541 beams, 20 m, Gaussian noise) cast in a raster whose non-free cells are solid."""

    def __init__(self, grid: OccupancyMap, *, beams: int = 541, fov_rad: float = math.radians(270.0),
                 range_max: float = 20.0, noise_m: float = 0.012, rng: np.random.Generator | None = None) -> None:
        self.grid = grid
        self.solid = grid.data != FREE
        self.clear_m = ndimage.distance_transform_edt(~self.solid) * grid.resolution
        self.angle_min = -fov_rad / 2.0
        self.angle_increment = fov_rad / (beams - 1)
        self.angles = self.angle_min + np.arange(beams) * self.angle_increment
        self.range_min, self.range_max = 0.05, range_max
        self.noise_m = noise_m
        self.rng = rng or np.random.default_rng(7)

    def _clearance(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        g = self.grid
        col = np.floor((x - g.origin[0]) / g.resolution).astype(np.intp)
        row = np.floor((y - g.origin[1]) / g.resolution).astype(np.intp)
        inside = (col >= 0) & (col < g.width) & (row >= 0) & (row < g.height)
        out = np.zeros(x.shape)
        out[inside] = self.clear_m[row[inside], col[inside]]
        return out

    def clearance(self, x: float, y: float) -> float:
        return float(self._clearance(np.array([x]), np.array([y]))[0])

    def scan(self, pose: Pose, mount: Pose = MOUNT) -> np.ndarray:
        """float32 ranges from the laser at ``pose`` ∘ ``mount``; +inf where nothing is within range_max."""
        lx, ly, lth = compose(pose, mount)
        a = lth + self.angles
        dx, dy = np.cos(a), np.sin(a)
        t = np.zeros(a.size)
        active = np.ones(a.size, dtype=bool)
        step_min = 0.25 * self.grid.resolution
        for _ in range(4000):
            if not active.any():
                break
            idx = np.nonzero(active)[0]
            c = self._clearance(lx + t[idx] * dx[idx], ly + t[idx] * dy[idx])
            hit = c <= 0.0
            t[idx[~hit]] += np.maximum(c[~hit] - 0.5 * self.grid.resolution, step_min)
            done = hit | (t[idx] > self.range_max)
            active[idx[done]] = False
        ranges = t + self.rng.normal(0.0, self.noise_m, size=t.shape)
        ranges[t > self.range_max] = np.inf
        return ranges.astype(np.float32)


def random_route(laser: GridLaser, rng: np.random.Generator, *, length_m: float, clearance_m: float = 0.75,
                 max_clearance_m: float = 4.0, leg_m: tuple[float, float] = (1.5, 6.0)) -> list[Pose]:
    """Poses of straight legs through free space (clearance between ``clearance_m`` and ``max_clearance_m`` all
    along: inside the building, never out in open space where a laser sees nothing), about ``length_m`` long in
    total, from a random start with that clearance."""
    free = np.argwhere((laser.clear_m > clearance_m + laser.grid.resolution) & (laser.clear_m < max_clearance_m))
    if free.size == 0:
        raise ValueError("no cell of the map has that clearance")
    g = laser.grid
    row, col = free[rng.integers(free.shape[0])]
    x, y = g.origin[0] + (col + 0.5) * g.resolution, g.origin[1] + (row + 0.5) * g.resolution
    poses: list[Pose] = [(x, y, float(rng.uniform(-math.pi, math.pi)))]
    total, tries = 0.0, 0
    while total < length_m and tries < 400:
        tries += 1
        heading = float(rng.uniform(-math.pi, math.pi))
        want = float(rng.uniform(*leg_m))
        s = np.arange(0.05, want, 0.05)
        xs, ys = x + s * math.cos(heading), y + s * math.sin(heading)
        c = laser._clearance(xs, ys)
        ok = (c > clearance_m) & (c < max_clearance_m)
        n_ok = int(np.argmin(ok)) if not ok.all() else ok.size
        if n_ok * 0.05 < 1.0:
            continue
        x, y = float(xs[n_ok - 1]), float(ys[n_ok - 1])
        poses.append((x, y, heading))
        total += n_ok * 0.05
    return poses


@dataclass
class RunTrace:
    """Per scan: true-pose error of the published pose (m, rad), the filter's state and distance travelled."""

    errors_xy_m: list[float] = field(default_factory=list)
    errors_theta_rad: list[float] = field(default_factory=list)
    states: list[str] = field(default_factory=list)
    distance_m: list[float] = field(default_factory=list)
    times_s: list[float] = field(default_factory=list)


def run(amcl: Amcl, laser: GridLaser, truth: list[Pose], *, seed: int = 1, scan_period_s: float = 0.2,
        kidnap_at: int | None = None, scan_lag: int = 0) -> RunTrace:
    """Feed AMCL one scan per true pose (``scan_period_s`` apart, for the time axis). ``kidnap_at``: the robot is
    carried from truth[kidnap_at - 1] to truth[kidnap_at] without its wheels turning (odometry does not see it).
    ``scan_lag``: every scan is stamped that many periods late, so it goes to the filter with the odometry of a pose
    the robot reached later (truth[i + scan_lag], the last one at the end); errors are those of the pose the filter
    holds for the scan's stamp."""
    odom = Odometry(truth[0], rng=np.random.default_rng(seed + 20))
    odoms = []
    for i, true in enumerate(truth):
        if kidnap_at is not None and i == kidnap_at:
            odom.teleported(true)
        odoms.append(odom.step(true))
    trace = RunTrace()
    travelled, last = 0.0, truth[0]
    for i, true in enumerate(truth):
        if kidnap_at is not None and i == kidnap_at:
            last = true
        travelled += math.hypot(true[0] - last[0], true[1] - last[1])
        last = true
        o = odoms[min(i + scan_lag, len(odoms) - 1)]
        beams = select_beams(laser.scan(true), laser.angle_min, laser.angle_increment, laser.range_min,
                             laser.range_max, amcl.params)
        amcl.process(o, beams, MOUNT, i * scan_period_s)
        if amcl.map_odom is None:
            continue
        est = compose(amcl.map_odom, o)
        trace.errors_xy_m.append(math.hypot(est[0] - true[0], est[1] - true[1]))
        trace.errors_theta_rad.append(abs(float(wrap_angle(est[2] - true[2]))))
        trace.states.append(getattr(amcl, "state", "tracking"))
        trace.distance_m.append(travelled)
        trace.times_s.append(i * scan_period_s)
    return trace


def dense(poses: list[Pose], step_m: float = 0.05, step_rad: float = 0.05) -> list[Pose]:
    """Route poses every ``step_m`` / ``step_rad`` (synthetic.route)."""
    return list(route(poses, step_m, step_rad))
#: scans at 25 Hz while driving at 0.2 m/s (the paper's top speed): 8 mm between scans
SCAN_PERIOD_S = 0.04
SCAN_STEP_M = 0.2 * SCAN_PERIOD_S


@dataclass
class Trial:
    """Outcome of one kidnapping or corrupted-initial-pose run.

    ``detect_s``: time from the fault (kidnapping; for a wrong initial pose, the start) until the verdict said lost
    (None: never); ``outcome``: ``recovered`` (tracking at the end within 0.2 m), ``reports_lost`` (not tracking
    at the end: the filter says it cannot), ``tracking_wrong`` (tracking at the end more than 0.2 m off);
    ``wrong_tracking_s``: time the verdict said tracking while more than 0.5 m off after the fault.
    """

    detect_s: float | None
    outcome: str
    final_error_m: float
    wrong_tracking_s: float
    recovered_after_s: float | None


def _judge_trial(trace: RunTrace, fault_s: float) -> Trial:
    t = np.array(trace.times_s)
    e = np.array(trace.errors_xy_m)
    st = np.array(trace.states)
    after = t >= fault_s
    lost = np.nonzero(after & (st == "lost"))[0]
    detect = float(t[lost[0]] - fault_s) if lost.size else None
    wrong = float(np.count_nonzero(after & (st == "tracking") & (e > 0.5)) * SCAN_PERIOD_S)
    final_e = float(e[-1])
    if st[-1] != "tracking":
        outcome = "reports_lost"
    else:
        outcome = "recovered" if final_e <= 0.2 else "tracking_wrong"
    back = np.nonzero(after & (st == "tracking") & (e <= 0.2))[0]
    back = back[t[back] > t[lost[0]]] if lost.size else back
    return Trial(detect, outcome, final_e, wrong, float(t[back[0]] - fault_s) if back.size else None)


def kidnap_trial(grid: OccupancyMap, seed: int, params: AmclParams) -> Trial:
    """Track 6 m of route, be carried (without odometry seeing it) to a random pose at least 5 m away, drive 12 m
    more from there."""
    grid = axis_aligned(grid)
    laser = GridLaser(grid, rng=np.random.default_rng(seed))
    rng = np.random.default_rng(seed)
    a = dense(random_route(laser, rng, length_m=6.0), SCAN_STEP_M)
    for _ in range(50):
        b = dense(random_route(laser, rng, length_m=12.0), SCAN_STEP_M)
        if math.hypot(b[0][0] - a[-1][0], b[0][1] - a[-1][1]) >= 5.0:
            break
    amcl = Amcl(grid, params)
    amcl.set_initial_pose(a[0], np.diag([0.05 ** 2, 0.05 ** 2, 0.03 ** 2]))
    trace = run(amcl, laser, a + b, seed=seed, scan_period_s=SCAN_PERIOD_S, kidnap_at=len(a))
    return _judge_trial(trace, len(a) * SCAN_PERIOD_S)


def initial_pose_trial(grid: OccupancyMap, seed: int, params: AmclParams, offset_m: float = 2.0) -> Trial:
    """Start with an initial pose ``offset_m`` off the true one (random direction, Nav2's default spread of
    0.5 m / pi/12 around it) and drive 18 m."""
    grid = axis_aligned(grid)
    laser = GridLaser(grid, rng=np.random.default_rng(seed))
    rng = np.random.default_rng(seed)
    truth = dense(random_route(laser, rng, length_m=18.0), SCAN_STEP_M)
    bearing = float(rng.uniform(-math.pi, math.pi))
    x, y, th = truth[0]
    amcl = Amcl(grid, params)
    amcl.set_initial_pose((x + offset_m * math.cos(bearing), y + offset_m * math.sin(bearing), th))
    trace = run(amcl, laser, truth, seed=seed, scan_period_s=SCAN_PERIOD_S)
    # the fault is there from the start: count a "lost" verdict only, the first moments are localizing anyway
    return _judge_trial(trace, 0.0)
