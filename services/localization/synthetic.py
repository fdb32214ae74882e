"""Synthetic runs for AMCL tests and benchmarks: a rectangle world rendered to a grid, an exact laser, a route.

A world file (like the corridor world, ``corridor.toml``) is solid except its free rectangles, with obstacle
rectangles added back. ``render`` rasterises it like a map_server map; ``Laser`` casts rays against the exact
rectangles (LMS111-like: 270 deg at 0.5 deg, 20 m, Gaussian range noise); ``route`` walks a piecewise-linear path
through poses in small steps; ``Odometry`` integrates the true body motion with scale errors and noise.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from services.common.se2 import compose, wrap_angle
from services.localization.amcl import Amcl, AmclParams, select_beams
from services.localization.map_io import OccupancyMap

#: Table 3 goals joined by via points that keep the straight legs inside free space
TABLE3_ROUTE = [
    (0.0, 0.0, 0.0), (3.0, 0.1, 1.57), (3.0, 3.5, 0.0), (13.6, 3.2, -1.0), (24.4, 3.5, 1.57), (26.8, 6.6, 1.0),
    (23.5, 7.0, 1.57), (23.1, 13.4, -1.57), (23.5, 7.0, -2.5), (22.5, 3.3, 3.14), (0.0, 3.2, 2.0),
]


@dataclass
class World:
    free: np.ndarray        # (k, 4) [xmin, ymin, xmax, ymax]
    obstacles: np.ndarray   # (j, 4)
    extent: tuple[float, float, float, float]
    resolution: float

    @classmethod
    def load(cls, path: Path) -> World:
        w = tomllib.loads(path.read_text())
        extent = w["extent_m"] if "extent_m" in w else w["extent"]  # the simulator's key names, or the plain ones
        resolution = w["resolution_m"] if "resolution_m" in w else w["resolution"]
        return cls(np.array(w["free"], dtype=float), np.array(w.get("obstacles", []), dtype=float).reshape(-1, 4),
                   tuple(extent), float(resolution))

    def is_free(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        x, y = np.asarray(x)[..., None], np.asarray(y)[..., None]
        f, o = self.free, self.obstacles
        inside_free = ((x >= f[:, 0]) & (x < f[:, 2]) & (y >= f[:, 1]) & (y < f[:, 3])).any(axis=-1)
        inside_obstacle = ((x >= o[:, 0]) & (x < o[:, 2]) & (y >= o[:, 1]) & (y < o[:, 3])).any(axis=-1)
        return np.asarray(inside_free & ~inside_obstacle)

    def render(self) -> OccupancyMap:
        """The world as a grid: cells whose centre is free are 0, the rest 100; origin at the extent's corner."""
        x0, y0, x1, y1 = self.extent
        res = self.resolution
        cols, rows = round((x1 - x0) / res), round((y1 - y0) / res)
        cx = x0 + (np.arange(cols) + 0.5) * res
        cy = y0 + (np.arange(rows) + 0.5) * res
        free = self.is_free(cx[None, :].repeat(rows, 0), cy[:, None].repeat(cols, 1))
        return OccupancyMap(np.where(free, 0, 100).astype(np.int8), res, (x0, y0, 0.0))


class Laser:
    """Exact ray casting against the world's rectangles, with Gaussian range noise (m)."""

    def __init__(self, world: World, *, beams: int = 541, fov_rad: float = math.radians(270.0),
                 range_max: float = 20.0, noise_m: float = 0.012, rng: np.random.Generator | None = None) -> None:
        self.world = world
        self.angle_min = -fov_rad / 2.0
        self.angle_increment = fov_rad / (beams - 1)
        self.angles = self.angle_min + np.arange(beams) * self.angle_increment
        self.range_min, self.range_max = 0.05, range_max
        self.noise_m = noise_m
        self.rng = rng or np.random.default_rng(7)
        rects = np.vstack([world.free, world.obstacles])
        self.xs = np.unique(rects[:, [0, 2]])
        self.ys = np.unique(rects[:, [1, 3]])

    def scan(self, pose: tuple[float, float, float], mount: tuple[float, float, float]) -> np.ndarray:
        """float32 ranges of one scan from the laser at ``pose`` ∘ ``mount``; +inf where nothing is in range."""
        lx, ly, lth = compose(pose, mount)
        a = lth + self.angles
        dx, dy = np.cos(a)[:, None], np.sin(a)[:, None]
        with np.errstate(divide="ignore", invalid="ignore"):
            tx = (self.xs[None, :] - lx) / dx
            ty = (self.ys[None, :] - ly) / dy
        t = np.concatenate([tx, ty], axis=1)
        t[~np.isfinite(t) | (t <= 1e-9)] = np.inf
        t.sort(axis=1)
        probe = t + 1e-6
        with np.errstate(invalid="ignore"):
            blocked = ~self.world.is_free(lx + probe * dx, ly + probe * dy) & np.isfinite(t)
        first = np.where(blocked.any(axis=1), t[np.arange(t.shape[0]), blocked.argmax(axis=1)], np.inf)
        ranges = first + self.rng.normal(0.0, self.noise_m, size=first.shape)
        ranges[(first > self.range_max) | ~np.isfinite(first)] = np.inf
        return ranges.astype(np.float32)


def route(poses: list[tuple[float, float, float]], step_m: float = 0.05, step_rad: float = 0.05):
    """Yield true poses along straight legs between ``poses``; heading turns linearly (shortest way) on each leg."""
    yield poses[0]
    for (x0, y0, t0), (x1, y1, t1) in zip(poses, poses[1:]):
        dth = wrap_angle(t1 - t0)
        steps = max(1, math.ceil(max(math.hypot(x1 - x0, y1 - y0) / step_m, abs(dth) / step_rad)))
        for i in range(1, steps + 1):
            f = i / steps
            yield (x0 + f * (x1 - x0), y0 + f * (y1 - y0), t0 + f * dth)


class Odometry:
    """Dead reckoning from true poses: body-frame increments scaled (1 + scale error) plus Gaussian noise."""

    def __init__(self, start: tuple[float, float, float], *, scale_error: float = 0.01, noise_frac: float = 0.02,
                 rng: np.random.Generator | None = None) -> None:
        self.pose = (0.0, 0.0, 0.0)
        self._last_true = start
        self.scale = 1.0 + scale_error
        self.noise_frac = noise_frac
        self.rng = rng or np.random.default_rng(11)

    def teleported(self, true_pose: tuple[float, float, float]) -> None:
        """The robot was moved without its wheels turning (kidnapping): odometry does not see the jump."""
        self._last_true = true_pose

    def step(self, true_pose: tuple[float, float, float]) -> tuple[float, float, float]:
        x0, y0, t0 = self._last_true
        x1, y1, t1 = true_pose
        c, s = math.cos(t0), math.sin(t0)
        bx, by = c * (x1 - x0) + s * (y1 - y0), -s * (x1 - x0) + c * (y1 - y0)
        bt = wrap_angle(t1 - t0)
        n = self.rng.normal(0.0, self.noise_frac, size=3)
        bx, by = bx * self.scale * (1 + n[0]), by * self.scale * (1 + n[1])
        bt = bt * self.scale * (1 + n[2])
        self.pose = compose(self.pose, (bx, by, bt))
        self._last_true = true_pose
        return self.pose


def find_world(name: str = "corridor") -> Path | None:
    """The world file ``<name>.toml``: the simulator's package data, else the development data folder."""
    import os

    root = Path(__file__).resolve().parents[2]
    shared = Path(os.environ.get("ZAGV_SHARED", root.parent / "shared"))
    for candidate in (root / "services" / "sim" / "worlds" / f"{name}.toml", shared / "worlds" / f"{name}.toml"):
        if candidate.is_file():
            return candidate
    return None


@dataclass
class RunResult:
    """Errors of the published map pose (map_odom ∘ odom) against the truth at every scan of a run."""

    errors_xy_m: np.ndarray
    errors_theta_rad: np.ndarray
    distance_m: np.ndarray  # distance travelled before each scan
    updates: int

    @property
    def rms_xy_m(self) -> float:
        return float(np.sqrt(np.mean(self.errors_xy_m ** 2)))

    @property
    def rms_theta_rad(self) -> float:
        return float(np.sqrt(np.mean(self.errors_theta_rad ** 2)))

    def settled_after_m(self, threshold_m: float) -> float | None:
        """Distance after which the error stays below ``threshold_m`` to the end (None: it never settles)."""
        above = np.nonzero(self.errors_xy_m >= threshold_m)[0]
        if above.size == 0:
            return float(self.distance_m[0])
        if above[-1] + 1 >= self.errors_xy_m.size:
            return None
        return float(self.distance_m[above[-1] + 1])


MOUNT = (0.45, 0.0, 0.0)


def drive(amcl: Amcl, world: World, truth: list[tuple[float, float, float]], *, seed: int = 1,
          mount: tuple[float, float, float] = MOUNT, odometry: Odometry | None = None) -> RunResult:
    """Feed AMCL one scan per true pose (odometry from the true increments) and record its errors."""
    laser = Laser(world, rng=np.random.default_rng(seed + 10))
    odom = odometry or Odometry(truth[0], rng=np.random.default_rng(seed + 20))
    params: AmclParams = amcl.params
    exy, eth, dist = [], [], []
    travelled = 0.0
    last = truth[0]
    for true in truth:
        travelled += math.hypot(true[0] - last[0], true[1] - last[1])
        last = true
        o = odom.step(true)
        beams = select_beams(laser.scan(true, mount), laser.angle_min, laser.angle_increment, laser.range_min,
                             laser.range_max, params)
        amcl.process(o, beams, mount)
        if amcl.map_odom is None:
            continue
        est = compose(amcl.map_odom, o)
        exy.append(math.hypot(est[0] - true[0], est[1] - true[1]))
        eth.append(abs(float(wrap_angle(est[2] - true[2]))))
        dist.append(travelled)
    return RunResult(np.array(exy), np.array(eth), np.array(dist), amcl.updates)
