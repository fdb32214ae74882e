"""Layered 2-D costmaps in the style of Nav2's costmap_2d: static, obstacle and inflation layers.

Cost codes (Nav2 ``cost_values.hpp``): 0 free, 1..252 inflated (252 = MAX_NON_OBSTACLE), 253 inscribed (the robot's
centre here means the footprint touches an obstacle), 254 lethal, 255 no information.

A costmap is a uint8 grid (row ``i`` along +y, column ``j`` along +x) whose cell (0, 0) has its outer corner at
``(origin_x, origin_y)`` in the costmap's frame. Each layer keeps its own state and writes into the master grid in
``update``; the master is rebuilt from scratch on every update (static, then obstacles by max, then inflation), so a
layer never has to undo what another wrote.

Inflation: with d the distance (m) from a cell centre to the nearest lethal cell centre,
``cost = 254`` at d = 0, ``253`` for d <= inscribed radius, ``252 * exp(-cost_scaling_factor * (d - inscribed))`` up to
``inflation_radius``, 0 beyond. d comes from an exact Euclidean distance transform (``services.common.gridops``),
computed on the window of the update bounds grown by the inflation radius.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from services.common import gridops

try:
    import services.nav._navops as _navops
except ImportError:  # built at install where a C compiler was available (setup.py); NumPy below otherwise
    _navops = None

FREE = 0
MAX_NON_OBSTACLE = 252
INSCRIBED = 253
LETHAL = 254
NO_INFORMATION = 255


# --------------------------------------------------------------------------- footprint


@dataclass(frozen=True)
class Footprint:
    """A circular footprint of ``radius_m`` or a polygon [(x, y), ...] in base_link (m)."""

    radius_m: float = 0.63
    polygon: tuple[tuple[float, float], ...] = ()

    def __post_init__(self) -> None:
        if self.polygon and len(self.polygon) < 3:
            raise ValueError(f"footprint polygon needs >= 3 points, got {len(self.polygon)}")
        if not self.polygon and not self.radius_m > 0:
            raise ValueError(f"footprint radius must be > 0 m, got {self.radius_m}")

    @property
    def is_circle(self) -> bool:
        return not self.polygon

    @property
    def inscribed_radius_m(self) -> float:
        """Largest circle about the origin inside the footprint (distance to the nearest edge)."""
        if self.is_circle:
            return self.radius_m
        pts = np.asarray(self.polygon, dtype=float)
        a, b = pts, np.roll(pts, -1, axis=0)
        return float(np.min(_point_segment_distance(np.zeros(2), a, b)))

    @property
    def circumscribed_radius_m(self) -> float:
        if self.is_circle:
            return self.radius_m
        return float(np.max(np.hypot(*np.asarray(self.polygon, dtype=float).T)))

    def outline(self, spacing_m: float) -> np.ndarray:
        """Points (n, 2) along the outline every ``spacing_m`` (for collision checks of a polygon)."""
        if self.is_circle:
            n = max(8, int(math.ceil(2 * math.pi * self.radius_m / spacing_m)))
            a = np.linspace(0, 2 * math.pi, n, endpoint=False)
            return np.column_stack([self.radius_m * np.cos(a), self.radius_m * np.sin(a)])
        pts = np.asarray(self.polygon, dtype=float)
        out = []
        for p, q in zip(pts, np.roll(pts, -1, axis=0)):
            n = max(1, int(math.ceil(np.hypot(*(q - p)) / spacing_m)))
            t = np.arange(n)[:, None] / n
            out.append(p + t * (q - p))
        return np.vstack(out)

    def contains(self, xy: np.ndarray) -> np.ndarray:
        """Whether points (n, 2) in base_link lie inside the footprint."""
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        if self.is_circle:
            within: np.ndarray = np.hypot(xy[:, 0], xy[:, 1]) <= self.radius_m
            return within
        pts = np.asarray(self.polygon, dtype=float)
        inside = np.zeros(len(xy), dtype=bool)
        for (x1, y1), (x2, y2) in zip(pts, np.roll(pts, -1, axis=0)):
            crosses = (y1 > xy[:, 1]) != (y2 > xy[:, 1])
            with np.errstate(divide="ignore", invalid="ignore"):
                x_at = x1 + (xy[:, 1] - y1) * (x2 - x1) / (y2 - y1)
            inside ^= crosses & (xy[:, 0] < x_at)
        return inside


def _point_segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ab = b - a
    t = np.clip(np.einsum("ij,ij->i", p - a, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-12), 0.0, 1.0)
    distance: np.ndarray = np.hypot(*(a + t[:, None] * ab - p).T)
    return distance


# --------------------------------------------------------------------------- grid


@dataclass
class Costmap2D:
    """A uint8 cost grid with its geometry: ``resolution`` m/cell, cell (0, 0) outer corner at the origin."""

    resolution: float
    origin_x: float
    origin_y: float
    cost: np.ndarray  # (height, width) uint8

    @classmethod
    def empty(cls, width: int, height: int, resolution: float, origin_x: float = 0.0, origin_y: float = 0.0,
              value: int = FREE) -> Costmap2D:
        return cls(resolution, origin_x, origin_y, np.full((height, width), value, dtype=np.uint8))

    @property
    def width(self) -> int:
        return int(self.cost.shape[1])

    @property
    def height(self) -> int:
        return int(self.cost.shape[0])

    def world_to_map(self, x: np.ndarray | float, y: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """(row i, column j) int arrays of the cells holding points (x, y) (may be out of bounds)."""
        j = np.floor((np.asarray(x) - self.origin_x) / self.resolution).astype(np.int64)
        i = np.floor((np.asarray(y) - self.origin_y) / self.resolution).astype(np.int64)
        return i, j

    def map_to_world(self, i: np.ndarray | np.integer | int,
                     j: np.ndarray | np.integer | int) -> tuple[np.ndarray, np.ndarray]:
        """Centre (x, y) in m of cells (i, j)."""
        x = self.origin_x + (np.asarray(j) + 0.5) * self.resolution
        y = self.origin_y + (np.asarray(i) + 0.5) * self.resolution
        return x, y

    def in_bounds(self, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        return (i >= 0) & (i < self.height) & (j >= 0) & (j < self.width)

    def cost_at(self, x: np.ndarray | float, y: np.ndarray | float, outside: int = NO_INFORMATION) -> np.ndarray:
        """Costs at world points; ``outside`` for points off the grid."""
        i, j = self.world_to_map(x, y)
        ok = self.in_bounds(i, j)
        out = np.full(np.shape(i), outside, dtype=np.uint8)
        out[ok] = self.cost[i[ok], j[ok]]
        return out


# --------------------------------------------------------------------------- layers

#: a window of the master grid in cells: rows i0..i1, columns j0..j1 (i1, j1 exclusive)
CellBounds = tuple[int, int, int, int]


def whole(master: Costmap2D) -> CellBounds:
    """The bounds that cover all of ``master``."""
    h, w = master.cost.shape
    return (0, 0, h, w)



class StaticLayer:
    """Cells of an occupancy grid (int8: -1 unknown, 0..100): >= ``lethal_threshold`` lethal, -1 no information
    (or free when ``track_unknown`` is off), the rest free. Sampled by nearest cell into any costmap geometry."""

    def __init__(self, lethal_threshold: int = 65, track_unknown: bool = True) -> None:
        self.lethal_threshold = lethal_threshold
        self.track_unknown = track_unknown
        self.grid: Costmap2D | None = None

    def set_map(self, data: np.ndarray, resolution: float, origin_x: float, origin_y: float) -> None:
        """``data`` int8 (height, width), row 0 at origin (OccupancyGrid layout)."""
        occ = np.asarray(data, dtype=np.int8)
        cost = np.zeros(occ.shape, dtype=np.uint8)
        cost[occ >= self.lethal_threshold] = LETHAL
        if self.track_unknown:
            cost[occ < 0] = NO_INFORMATION
        self.grid = Costmap2D(resolution, origin_x, origin_y, cost)

    def update(self, master: Costmap2D, bounds: CellBounds | None = None) -> None:
        """Write the map into ``master`` within ``bounds`` (None: the whole grid)."""
        i0, j0, i1, j1 = whole(master) if bounds is None else bounds
        target = master.cost[i0:i1, j0:j1]
        if self.grid is None:
            target[:] = NO_INFORMATION if self.track_unknown else FREE
            return
        g = self.grid
        if (g.resolution == master.resolution and g.origin_x == master.origin_x and g.origin_y == master.origin_y
                and g.cost.shape == master.cost.shape):
            np.copyto(target, g.cost[i0:i1, j0:j1])
            return
        ii, jj = np.indices(target.shape)
        x, y = master.map_to_world(ii + i0, jj + j0)
        target[:] = g.cost_at(x, y, outside=NO_INFORMATION if self.track_unknown else FREE)


@dataclass
class ScanObservation:
    """A laser scan in the costmap frame: sensor origin (m; one for the scan, or one per beam when the scan is
    de-skewed for the robot's motion while it was taken) and per-beam angle (rad, costmap frame), range."""

    origin_x: float | np.ndarray
    origin_y: float | np.ndarray
    angles: np.ndarray
    ranges: np.ndarray
    range_min: float
    range_max: float


@dataclass
class ObstacleLayer:
    """Marks scan end points and clears the cells each beam passes through (ray tracing).

    Per beam: a finite range in [range_min, range_max) marks its end cell when within ``obstacle_max_range_m`` and
    clears the cells before it up to ``raytrace_max_range_m``. A beam without a return (+inf, or >= range_max,
    which SICK drivers report for no echo) clears up to ``raytrace_max_range_m`` and marks nothing, so obstacles
    that went away disappear (Nav2's ``inf_is_valid``); NaN and ranges below range_min are ignored.
    """

    obstacle_max_range_m: float = 2.5
    raytrace_max_range_m: float = 3.0
    footprint_clearing: bool = True
    grid: np.ndarray | None = None  # uint8 LETHAL/FREE, master's shape
    #: cells whose marks are not applied (master's shape): the static map's walls grown by a tolerance
    ignore: np.ndarray | None = None
    _geometry: tuple[float, float, float] = (0.0, 0.0, 0.0)
    marked_cells: int = field(default=0)

    def _ensure(self, master: Costmap2D) -> None:
        geo = (master.resolution, master.origin_x, master.origin_y)
        if self.grid is None or self.grid.shape != master.cost.shape:
            self.grid = np.zeros(master.cost.shape, dtype=np.uint8)
            self._geometry = geo
        elif geo != self._geometry:
            # rolling window moved: shift what is kept
            di = int(round((geo[2] - self._geometry[2]) / master.resolution))
            dj = int(round((geo[1] - self._geometry[1]) / master.resolution))
            self.grid = _shift(self.grid, di, dj)
            self._geometry = geo

    def clear(self) -> None:
        if self.grid is not None:
            self.grid[:] = FREE

    def add_scan(self, master: Costmap2D, obs: ScanObservation) -> None:
        self._ensure(master)
        assert self.grid is not None
        r = np.asarray(obs.ranges, dtype=np.float64)
        a = np.asarray(obs.angles, dtype=np.float64)
        finite = np.isfinite(r)
        hit = finite & (r >= obs.range_min) & (r < obs.range_max)
        no_return = (np.isposinf(r)) | (finite & (r >= obs.range_max))
        use = hit | no_return
        if not use.any():
            return
        ox = np.broadcast_to(np.asarray(obs.origin_x, dtype=np.float64), a.shape)[use]
        oy = np.broadcast_to(np.asarray(obs.origin_y, dtype=np.float64), a.shape)[use]
        a, r, hit = a[use], r[use], hit[use]
        clear_len = np.where(hit, np.minimum(r, self.raytrace_max_range_m), self.raytrace_max_range_m)
        res = master.resolution
        step = 0.5 * res
        n_steps = int(np.ceil(clear_len.max() / step)) if len(clear_len) else 0
        mark = hit & (r <= self.obstacle_max_range_m)
        cos_a, sin_a = np.cos(a), np.sin(a)
        mx = ox[mark] + r[mark] * cos_a[mark]
        my = oy[mark] + r[mark] * sin_a[mark]
        if _navops is not None and self.grid.flags.c_contiguous:
            _navops.raytrace(self.grid, float(master.origin_x), float(master.origin_y), float(res),
                             np.ascontiguousarray(ox), np.ascontiguousarray(oy), cos_a, sin_a, clear_len,
                             n_steps, step, mx, my, FREE, LETHAL)
        else:
            self._raytrace_numpy(master, ox, oy, cos_a, sin_a, clear_len, n_steps, step, mx, my)
        self.marked_cells = int(np.count_nonzero(self.grid))

    def _raytrace_numpy(self, master: Costmap2D, ox: np.ndarray, oy: np.ndarray, cos_a: np.ndarray,
                        sin_a: np.ndarray, clear_len: np.ndarray, n_steps: int, step: float, mx: np.ndarray,
                        my: np.ndarray) -> None:
        """Clear each ray's cells up to (not including) its end cell, then mark the endpoints ``mx``, ``my``
        (``_navops.raytrace`` in NumPy: the fallback, and the reference in tests)."""
        assert self.grid is not None
        res = master.resolution
        if n_steps > 0:
            t = np.arange(n_steps) * step
            d = np.minimum(t[None, :], clear_len[:, None])
            valid = t[None, :] < (clear_len[:, None] - 0.5 * res)
            xs = ox[:, None] + d * cos_a[:, None]
            ys = oy[:, None] + d * sin_a[:, None]
            i, j = master.world_to_map(xs[valid], ys[valid])
            ok = master.in_bounds(i, j)
            self.grid[i[ok], j[ok]] = FREE
        if len(mx):
            i, j = master.world_to_map(mx, my)
            ok = master.in_bounds(i, j)
            self.grid[i[ok], j[ok]] = LETHAL

    def clear_footprint(self, master: Costmap2D, x: float, y: float, theta: float, footprint: Footprint) -> None:
        """Clear cells under the robot (its own body is never an obstacle)."""
        self._ensure(master)
        assert self.grid is not None
        rad = footprint.circumscribed_radius_m
        i0, j0 = map(int, master.world_to_map(x - rad, y - rad))
        i1, j1 = map(int, master.world_to_map(x + rad, y + rad))
        i0, j0 = max(i0, 0), max(j0, 0)
        i1, j1 = min(i1, master.height - 1), min(j1, master.width - 1)
        if i1 < i0 or j1 < j0:
            return
        ii, jj = np.mgrid[i0:i1 + 1, j0:j1 + 1]
        cx, cy = master.map_to_world(ii, jj)
        c, s = math.cos(theta), math.sin(theta)
        dx, dy = cx - x, cy - y
        local = np.column_stack([(c * dx + s * dy).ravel(), (-s * dx + c * dy).ravel()])
        inside = footprint.contains(local).reshape(ii.shape)
        self.grid[ii[inside], jj[inside]] = FREE

    def update(self, master: Costmap2D, bounds: CellBounds | None = None) -> None:
        """Marks raise ``master`` (max) within ``bounds``; unknown cells stay unknown unless marked."""
        self._ensure(master)
        assert self.grid is not None
        i0, j0, i1, j1 = whole(master) if bounds is None else bounds
        target, marks = master.cost[i0:i1, j0:j1], self.grid[i0:i1, j0:j1]
        if self.ignore is not None and self.ignore.shape == master.cost.shape:
            marks = np.where(self.ignore[i0:i1, j0:j1], FREE, marks).astype(np.uint8)
        np.maximum(target, marks, out=target, where=(target != NO_INFORMATION) | (marks > 0))


def _shift(grid: np.ndarray, di: int, dj: int, fill: int = FREE) -> np.ndarray:
    """Content of ``grid`` seen from an origin moved by (di, dj) cells."""
    out = np.full_like(grid, fill)
    h, w = grid.shape
    if abs(di) >= h or abs(dj) >= w:
        return out
    src_i = slice(max(di, 0), h + min(di, 0))
    dst_i = slice(max(-di, 0), h + min(-di, 0))
    src_j = slice(max(dj, 0), w + min(dj, 0))
    dst_j = slice(max(-dj, 0), w + min(-dj, 0))
    out[dst_i, dst_j] = grid[src_i, src_j]
    return out


@dataclass
class InflationLayer:
    """Exponential inflation around lethal cells (module docstring). ``distance_m`` keeps the last distance field
    (m to the nearest lethal cell), which the planner uses for its clearance preference."""

    inscribed_radius_m: float = 0.63
    inflation_radius_m: float = 0.645
    cost_scaling_factor: float = 10.0
    inflate_unknown: bool = False
    distance_m: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.inflation_radius_m < 0 or self.inscribed_radius_m < 0 or self.cost_scaling_factor < 0:
            raise ValueError("inflation radii and cost_scaling_factor must be >= 0")

    def cost_of_distance(self, d: np.ndarray) -> np.ndarray:
        """Nav2's computeCost over distances ``d`` (m)."""
        d = np.asarray(d, dtype=np.float64)
        out = np.zeros(d.shape, dtype=np.uint8)
        r_in, r_out = self.inscribed_radius_m + 1e-6, self.inflation_radius_m + 1e-6  # cell multiples: 6 * 0.05 > 0.3
        band = (d > r_in) & (d <= r_out)
        out[band] = (MAX_NON_OBSTACLE * np.exp(-self.cost_scaling_factor * (d[band] - self.inscribed_radius_m)))\
            .astype(np.uint8)
        out[d <= r_in] = INSCRIBED
        out[d <= 0.0] = LETHAL
        return out

    def update(self, master: Costmap2D, bounds: CellBounds | None = None) -> None:
        """Inflate ``master`` in place within ``bounds`` (None: the whole grid)."""
        h, w = master.cost.shape
        i0, j0, i1, j1 = whole(master) if bounds is None else bounds
        pad = int(math.ceil(self.inflation_radius_m / master.resolution)) + 1
        wi0, wj0, wi1, wj1 = max(i0 - pad, 0), max(j0 - pad, 0), min(i1 + pad, h), min(j1 + pad, w)
        window = master.cost[wi0:wi1, wj0:wj1]
        source = window == LETHAL
        if self.inflate_unknown:
            source |= window == NO_INFORMATION
        if self.distance_m is None or self.distance_m.shape != master.cost.shape:
            self.distance_m = np.full(master.cost.shape, np.inf, dtype=np.float32)
        if not source.any():
            self.distance_m[i0:i1, j0:j1] = np.inf
            return
        d = gridops.distance_transform_edt(~source, sampling=master.resolution)
        d = d[i0 - wi0:i1 - wi0, j0 - wj0:j1 - wj0]
        self.distance_m[i0:i1, j0:j1] = d
        inflated = self.cost_of_distance(d)
        target = master.cost[i0:i1, j0:j1]
        unknown = target == NO_INFORMATION
        np.maximum(target, inflated, out=target)
        target[unknown] = np.where(inflated[unknown] >= INSCRIBED, inflated[unknown], NO_INFORMATION)


# --------------------------------------------------------------------------- layered costmaps


class LayeredCostmap:
    """Master grid = static, then obstacles (max), then inflation; ``update`` rebuilds it."""

    def __init__(self, master: Costmap2D, static: StaticLayer, obstacles: ObstacleLayer | None,
                 inflation: InflationLayer, footprint: Footprint) -> None:
        self.master = master
        self.static = static
        self.obstacles = obstacles
        self.inflation = inflation
        self.footprint = footprint

    def update(self, bounds: CellBounds | None = None) -> None:
        """Rebuild the master grid within ``bounds`` (None: all of it), layer by layer."""
        self.static.update(self.master, bounds)
        if self.obstacles is not None:
            self.obstacles.update(self.master, bounds)
        self.inflation.update(self.master, bounds)

    def add_scan(self, obs: ScanObservation) -> None:
        if self.obstacles is not None:
            self.obstacles.add_scan(self.master, obs)

    def clear_obstacles(self) -> None:
        if self.obstacles is not None:
            self.obstacles.clear()

    def clear_footprint(self, x: float, y: float, theta: float) -> None:
        if self.obstacles is not None and self.obstacles.footprint_clearing:
            self.obstacles.clear_footprint(self.master, x, y, theta, self.footprint)


class GlobalCostmap(LayeredCostmap):
    """Costmap over the whole static map (its geometry follows the map).

    Scan marks within ``static_wall_tolerance_m`` of a wall of the static map are not applied: they are that wall
    seen again, displaced by localization and timing error, and a path-planning costmap that keeps them (the global
    costmap never forgets a mark no beam passes through) narrows every doorway the robot has looked at until the
    planner finds no way through. The local costmap, which the controller checks trajectories against, keeps them.

    Updates are incremental, like Nav2's updateBounds/updateCosts: scans and footprint clearing only change cells
    within their reach of the robot, so ``update`` recomputes that window (grown by the inflation radius) and
    keeps the rest of the master grid. A new map or cleared obstacles recompute everything.
    """

    def __init__(self, master: Costmap2D, static: StaticLayer, obstacles: ObstacleLayer | None,
                 inflation: InflationLayer, footprint: Footprint, static_wall_tolerance_m: float = 0.0) -> None:
        super().__init__(master, static, obstacles, inflation, footprint)
        self.static_wall_tolerance_m = static_wall_tolerance_m
        self._full = True
        self._dirty: list[float] | None = None  # world x_min, y_min, x_max, y_max changed since the last update

    def set_map(self, data: np.ndarray, resolution: float, origin_x: float, origin_y: float) -> None:
        self.static.set_map(data, resolution, origin_x, origin_y)
        self.master = Costmap2D(resolution, origin_x, origin_y, np.zeros(np.shape(data), dtype=np.uint8))
        if self.obstacles is not None:
            self.obstacles.grid = None
            self.obstacles.ignore = None
            walls = self.static.grid.cost == LETHAL if self.static.grid is not None else None
            if self.static_wall_tolerance_m > 0 and walls is not None and walls.any():
                self.obstacles.ignore = (gridops.distance_transform_edt(~walls, sampling=resolution)
                                         <= self.static_wall_tolerance_m + 1e-6)
        self.inflation.distance_m = None
        self._full = True
        self.update()

    def _touch(self, x: float, y: float, reach_m: float) -> None:
        box = [x - reach_m, y - reach_m, x + reach_m, y + reach_m]
        d = self._dirty
        self._dirty = box if d is None else [min(d[0], box[0]), min(d[1], box[1]), max(d[2], box[2]),
                                             max(d[3], box[3])]

    def add_scan(self, obs: ScanObservation) -> None:
        super().add_scan(obs)
        if self.obstacles is not None:
            reach = max(self.obstacles.raytrace_max_range_m, self.obstacles.obstacle_max_range_m)
            ox, oy = np.asarray(obs.origin_x), np.asarray(obs.origin_y)
            spread = float(max(np.ptp(ox), np.ptp(oy))) if ox.size > 1 else 0.0
            self._touch(float(ox.mean()), float(oy.mean()), reach + spread + self.master.resolution)

    def clear_footprint(self, x: float, y: float, theta: float) -> None:
        super().clear_footprint(x, y, theta)
        self._touch(x, y, self.footprint.circumscribed_radius_m + self.master.resolution)

    def clear_obstacles(self) -> None:
        super().clear_obstacles()
        self._full = True

    def update(self, bounds: CellBounds | None = None) -> None:
        """Recompute what changed since the last update (``bounds``: exactly that window instead)."""
        if bounds is not None:
            super().update(bounds)
            return
        m = self.master
        static = self.static.grid
        same_geometry = (static is not None and static.cost.shape == m.cost.shape
                         and static.resolution == m.resolution and static.origin_x == m.origin_x
                         and static.origin_y == m.origin_y)
        if self._full or not same_geometry or (self.obstacles is not None and self.obstacles.grid is None):
            super().update()
            self._full = False
            self._dirty = None
            return
        if self._dirty is None:
            return  # nothing changed since the last update
        x0, y0, x1, y1 = self._dirty
        self._dirty = None
        pad = int(math.ceil(self.inflation.inflation_radius_m / m.resolution)) + 1
        i0, j0 = map(int, m.world_to_map(x0, y0))
        i1, j1 = map(int, m.world_to_map(x1, y1))
        i0, j0 = max(i0 - pad, 0), max(j0 - pad, 0)
        i1, j1 = min(i1 + pad + 1, m.height), min(j1 + pad + 1, m.width)
        if i1 > i0 and j1 > j0:
            super().update((i0, j0, i1, j1))


class RollingCostmap(LayeredCostmap):
    """A ``size_m`` square window centred on the robot; its origin snaps to whole cells as it follows."""

    def __init__(self, size_m: float, resolution: float, static: StaticLayer, obstacles: ObstacleLayer,
                 inflation: InflationLayer, footprint: Footprint) -> None:
        n = int(round(size_m / resolution))
        super().__init__(Costmap2D.empty(n, n, resolution, -size_m / 2, -size_m / 2), static, obstacles, inflation,
                         footprint)

    def recentre(self, x: float, y: float) -> None:
        m = self.master
        half = m.width * m.resolution / 2
        m.origin_x = math.floor((x - half) / m.resolution) * m.resolution
        m.origin_y = math.floor((y - half) / m.resolution) * m.resolution
        if self.obstacles is not None:
            self.obstacles._ensure(m)
