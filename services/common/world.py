"""The simulated 2-D world: an occupancy raster, dynamic rectangles, ray casting, collision, map rendering.

A world is an axis-aligned raster of ``resolution_m`` cells covering ``extent`` = [x_min, y_min, x_max, y_max]
(map frame, m). Cell (row r, column c) covers x in [x_min + c*res, x_min + (c+1)*res) and likewise y; row 0 is at
y_min. Cells are solid or free. Built-in worlds (``services/common/worlds/<name>.toml``) are solid everywhere except
their ``free`` rectangles, with ``obstacles`` rectangles made solid again and ``glass`` rectangles solid but
transparent to the lidar (the robot collides with them, the beams pass; the rendered map shows them, as a building
plan would); any ROS map YAML can be loaded instead (occupied and unknown cells are solid; a yawed origin is
resampled onto an axis-aligned raster). Everything outside the extent is solid.

Collision is exact geometry, as the lidar sees it: ``clearance_m(x, y)`` is the Euclidean distance from the point
itself (not its cell's centre) to the nearest solid cell square, min over squares of |max(|p - c| - h, 0)| (c the
square's centre, h half a cell). Only solid cells with a free 4-neighbour can be nearest (a k-d tree of their
centres); the nearest square's centre lies within d_c + h (sqrt(2) - 1) of p, d_c the nearest centre's distance,
since a square lies between its inscribed and circumscribed discs.

Dynamic obstacles are rectangles outside the raster (so adding one costs nothing): ray casting and collision test
them analytically. They appear and vanish on a schedule (sim time) or on request.

Ray casting marches every beam at once (numpy, vectorised over beams) through the raster: at each iteration a beam
jumps by the largest of three distances that are all free of solid cells: (a) the clearance from a precomputed
Euclidean distance transform (no solid cell centre closer than ``edt``, so nothing within ``edt - sqrt(2)`` cells),
(b) the distance to leave its current row, or to reach the end of the free run of that row in its x direction,
whichever comes first, and (c) the same along its column. (b) and (c) include the exact DDA step to the next
cell, so beams stop exactly on the face of the first solid cell, as a grid-exact DDA would; far from walls they
jump metres at a time and along walls a row or column at a time.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Iterable
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from services.common.grid import axis_aligned
from services.common.map_io import OccupancyMap
from services.common.ros_map import write_ros_map

SQRT2 = math.sqrt(2.0)


class WorldError(ValueError):
    """A world file or map that cannot be used; the message names the file and what is wrong."""


@dataclass
class DynamicObstacle:
    """A rectangle [x_min, y_min, x_max, y_max] (m); ``appear_at_s``/``vanish_at_s`` (sim s) schedule it."""

    id: str
    rect: tuple[float, float, float, float]
    active: bool = False
    appear_at_s: float | None = None
    vanish_at_s: float | None = None


@dataclass
class Goal:
    id: str
    pose: tuple[float, float, float]


@dataclass
class World:
    """Raster + dynamic rectangles. Build with ``from_solid``, ``load_builtin``, ``load_toml`` or ``load_map_yaml``."""

    name: str
    resolution_m: float
    origin_xy: tuple[float, float]
    solid: np.ndarray  # bool [rows, cols], row 0 at origin y
    start_pose: tuple[float, float, float] = (0.0, 0.0, 0.0)
    goals: list[Goal] = field(default_factory=list)
    dynamic: dict[str, DynamicObstacle] = field(default_factory=dict)
    #: solid cells the lidar sees through (glass walls and doors): they stop the robot, not the beams
    glass: np.ndarray | None = None
    #: the robots of a multi-robot world (``[[robots]]`` with ``id`` and ``start`` [x, y, theta]), in order
    robots: list[tuple[str, tuple[float, float, float]]] = field(default_factory=list)

    def __post_init__(self) -> None:
        if self.resolution_m <= 0 or not math.isfinite(self.resolution_m):
            raise WorldError(f"world {self.name}: resolution must be > 0 m, got {self.resolution_m}")
        if self.solid.ndim != 2 or self.solid.size == 0:
            raise WorldError(f"world {self.name}: empty raster")
        self.solid = np.ascontiguousarray(self.solid, dtype=bool)
        rows, cols = self.solid.shape
        # one solid cell of padding all round: rays and lookups never leave the padded raster
        padded = np.ones((rows + 2, cols + 2), dtype=bool)
        padded[1:-1, 1:-1] = self.solid
        self._cols_p = cols + 2
        self._rows_p = rows + 2
        edt = ndimage.distance_transform_edt(~padded).astype(np.float32)  # cells, centre to nearest solid centre
        self._edt_flat = edt.ravel()
        # collision sees every solid cell (glass included), exactly: the faces of the squares, as the lidar does
        self._boundary_tree = _boundary_tree(padded, self.origin_xy, self.resolution_m)
        self._solid_flat_collision = padded.ravel().copy()
        # ray casting sees the opaque cells only
        if self.glass is not None:
            if self.glass.shape != self.solid.shape:
                raise WorldError(f"world {self.name}: glass mask {self.glass.shape} != raster {self.solid.shape}")
            self.glass = np.ascontiguousarray(self.glass, dtype=bool) & self.solid
            padded[1:-1, 1:-1] &= ~self.glass
            edt = ndimage.distance_transform_edt(~padded).astype(np.float32)
        self._solid_flat = padded.ravel()
        # free cells: the clearance in cells (>= 0); solid cells: -1, so one lookup tells both
        self._clear_flat = np.where(padded, -1.0, np.maximum(edt - SQRT2, 0.0)).astype(np.float64).ravel()
        self._runs_flat = _free_run_table(padded)
        self._active_rects = np.zeros((0, 4))
        self._refresh_rects()

    # ------------------------------------------------------------------ geometry

    @property
    def shape(self) -> tuple[int, int]:
        return self.solid.shape

    @property
    def extent(self) -> tuple[float, float, float, float]:
        rows, cols = self.solid.shape
        x0, y0 = self.origin_xy
        return x0, y0, x0 + cols * self.resolution_m, y0 + rows * self.resolution_m

    def cell_of(self, x: float, y: float) -> tuple[int, int]:
        """(row, col) of the cell holding (x, y) (may lie outside the raster)."""
        return (math.floor((y - self.origin_xy[1]) / self.resolution_m),
                math.floor((x - self.origin_xy[0]) / self.resolution_m))

    def _padded_flat_index(self, x: float, y: float) -> int:
        r, c = self.cell_of(x, y)
        r = min(max(r + 1, 0), self._rows_p - 1)
        c = min(max(c + 1, 0), self._cols_p - 1)
        return int(r * self._cols_p + c)

    def is_solid(self, x: float, y: float) -> bool:
        """Static raster only; outside the extent is solid."""
        r, c = self.cell_of(x, y)
        rows, cols = self.solid.shape
        return not (0 <= r < rows and 0 <= c < cols) or bool(self.solid[r, c])

    def clearance_m(self, x: float, y: float, exact_within_m: float = math.inf) -> float:
        """Exact distance (m) from the point (x, y) to the nearest solid cell square (glass and outside the extent
        included) or active dynamic rectangle; 0 inside a solid cell.

        Where the cell's distance transform E (m, cell centre to the nearest solid centre) proves the raster farther
        than ``exact_within_m`` (E - sqrt(2) res > it: the point is within res/sqrt(2) of its cell centre and a square
        within res/sqrt(2) of its centre), that lower bound is returned instead: a contact test against a radius
        needs exactness only near the radius, and the bound costs one lookup.
        """
        i = self._padded_flat_index(x, y)
        lower = (float(self._edt_flat[i]) - SQRT2) * self.resolution_m
        if self._solid_flat_collision[i]:
            d = 0.0
        elif lower > exact_within_m:
            d = lower
        else:
            d = _distance_to_squares(self._boundary_tree, x, y, self.resolution_m / 2.0)
        for x0, y0, x1, y1 in self._active_rects_list:
            dx = max(x0 - x, 0.0, x - x1)
            dy = max(y0 - y, 0.0, y - y1)
            d = min(d, math.hypot(dx, dy))
        return d

    def circle_collides(self, x: float, y: float, radius_m: float) -> bool:
        """Whether a disc of ``radius_m`` at (x, y) touches anything solid."""
        return self.clearance_m(x, y) < radius_m

    # ------------------------------------------------------------------ dynamic obstacles

    def _refresh_rects(self) -> None:
        rects = [o.rect for o in self.dynamic.values() if o.active]
        self._active_rects = np.asarray(rects, dtype=float).reshape(-1, 4)
        self._active_rects_list = [tuple(map(float, r)) for r in rects]

    def set_obstacle(self, oid: str, rect: tuple[float, float, float, float] | list[float] | None) -> None:
        """Add/replace and activate obstacle ``oid`` (rect None: activate a predefined one)."""
        if rect is None or len(rect) == 0:
            if oid not in self.dynamic:
                raise WorldError(f"no obstacle {oid!r} in world {self.name}; give a rect to add one")
            self.dynamic[oid].active = True
        else:
            self.dynamic[oid] = DynamicObstacle(oid, _check_rect(rect, f"obstacle {oid!r}"), active=True)
        self._refresh_rects()

    def remove_obstacle(self, oid: str) -> None:
        if oid not in self.dynamic or not self.dynamic[oid].active:
            raise WorldError(f"no active obstacle {oid!r}")
        self.dynamic[oid].active = False
        self._refresh_rects()

    def clear_obstacles(self) -> None:
        for o in self.dynamic.values():
            o.active = False
        self._refresh_rects()

    def active_obstacle_ids(self) -> list[str]:
        return sorted(oid for oid, o in self.dynamic.items() if o.active)

    def apply_schedule(self, now_s: float) -> bool:
        """Activate/deactivate scheduled obstacles at sim time ``now_s``; True when something changed."""
        changed = False
        for o in self.dynamic.values():
            if o.appear_at_s is not None and now_s >= o.appear_at_s and not o.active and \
                    (o.vanish_at_s is None or now_s < o.vanish_at_s):
                o.active = changed = True
                o.appear_at_s = None
            if o.vanish_at_s is not None and now_s >= o.vanish_at_s:
                if o.active:
                    changed = True
                o.active = False
                o.vanish_at_s = None
        if changed:
            self._refresh_rects()
        return changed

    # ------------------------------------------------------------------ ray casting

    def raycast(self, x: float, y: float, angles_rad: np.ndarray, max_range_m: float,
                max_iterations: int = 2000) -> np.ndarray:
        """Range (m) along each world-frame angle from (x, y) to the first solid cell or active dynamic rectangle;
        ``max_range_m`` where nothing is hit within it. A non-finite pose or angle is a ValueError."""
        angles = np.asarray(angles_rad, dtype=np.float64)
        if not (math.isfinite(x) and math.isfinite(y) and np.isfinite(angles).all()):
            raise ValueError(f"raycast from a non-finite pose or angle: x={x}, y={y}, "
                             f"{int(np.count_nonzero(~np.isfinite(angles)))} non-finite of {angles.size} angles")
        res = self.resolution_m
        n = angles.shape[0]
        cols = self._cols_p
        gx = (x - self.origin_xy[0]) / res + 1.0  # padded cell coordinates
        gy = (y - self.origin_xy[1]) / res + 1.0
        max_t = max_range_m / res
        if not (0.0 <= gx < cols and 0.0 <= gy < self._rows_p) or self._solid_flat[int(gy) * cols + int(gx)]:
            ranges = np.zeros(n)
        else:
            ranges = self._march(gx, gy, angles, max_t, max_iterations) * res
            np.minimum(ranges, max_range_m, out=ranges)
        if self._active_rects.shape[0]:
            ranges = np.minimum(ranges, _ray_rects(x, y, np.asarray(angles_rad, dtype=np.float64),
                                                   self._active_rects, max_range_m))
        return ranges

    def _march(self, gx: float, gy: float, angles: np.ndarray, max_t: float, max_iterations: int,
               compact_every: int = 6) -> np.ndarray:
        """Distances (cells) to the first solid cell from padded cell coordinates (gx, gy); > max_t: no hit.

        Beams are stacked as 2 x n arrays; a finished beam stops advancing (its step is multiplied by 0) and the
        arrays are compacted every ``compact_every`` iterations, which keeps numpy calls per iteration few.
        """
        n = angles.shape[0]
        d = np.empty((2, n))
        d[0] = np.cos(angles)
        d[1] = np.sin(angles)
        d[d == 0.0] = 1e-12  # an axis-parallel beam: its exit distance along that axis becomes huge
        inv_d = 1.0 / d
        side = (d > 0.0).astype(np.float64)  # the cell face a beam exits through: floor + 1 when moving up
        # a beam moving down an axis that sits exactly on a cell face is in the cell below that face
        nudge = np.where(d < 0.0, -1e-9, 0.0)
        cells = self._solid_flat.size
        # where each beam's free-run lengths live in the run table: x tables first, then y; minus, then plus
        run_offset = np.empty((2, n), dtype=np.intp)
        run_offset[0] = (d[0] > 0.0) * cells
        run_offset[1] = 2 * cells + (d[1] > 0.0) * cells
        origin = np.array([[gx], [gy]])
        cols = float(self._cols_p)
        # no step is longer than the range asked for: t stays finite however a beam lines up with the grid
        step_cap = max_t + 2.0
        clear = self._clear_flat
        runs = self._runs_flat
        t = np.zeros(n)
        out = np.empty(n)
        idx = np.arange(n)
        alive = np.ones(n, dtype=bool)
        for it in range(1, max_iterations + 1):
            p = d * t
            p += origin
            cell = np.floor(p + nudge)
            flat = (cell[1] * cols + cell[0]).astype(np.intp)  # exact integers in float64; no BLAS call
            clearance = clear.take(flat, mode="clip")  # a beam off the grid reads a corner: solid
            hit = clearance < 0.0
            exit_ = cell + side
            exit_ -= p
            exit_ *= inv_d  # distance to leave the cell along x (row 0) and along y (row 1)
            run_end = runs.take(run_offset + flat, mode="clip") * inv_d
            run_end += exit_  # distance to the end of the free run along x (row 0) and along y (row 1)
            np.minimum(run_end, exit_[::-1], out=run_end)  # ... but only while still in this row / column
            step = np.maximum(run_end.max(axis=0), clearance)
            np.fmin(step, step_cap, out=step)  # fmin: a NaN step becomes the cap too
            step += 1e-6
            np.greater(alive, hit, out=alive)  # alive and not hit
            step *= alive
            t += step
            if it % compact_every == 0:
                live = alive & (t < max_t)
                if not live.any():
                    break
                if live.sum() < 0.7 * live.size:
                    out[idx] = t
                    idx, t, alive = idx[live], t[live], alive[live]
                    d, inv_d, side, nudge = d[:, live], inv_d[:, live], side[:, live], nudge[:, live]
                    run_offset = run_offset[:, live]
        out[idx] = t
        return out

    # ------------------------------------------------------------------ rendering

    def render_pgm(self) -> np.ndarray:
        """uint8 image rows top (max y) first: 0 occupied, 254 free (trinary map_server values)."""
        img = np.where(self.solid, 0, 254).astype(np.uint8)
        return np.ascontiguousarray(img[::-1])

    def occupancy_map(self) -> OccupancyMap:
        """The raster as an occupancy grid (solid 100, free 0), row 0 at the origin: what map_server would load from
        ``write_map``'s files."""
        x0, y0 = self.origin_xy
        return OccupancyMap(np.where(self.solid, 100, 0).astype(np.int8), self.resolution_m, (x0, y0, 0.0))

    def write_map(self, prefix: str | Path) -> tuple[Path, Path]:
        """Write ``prefix.yaml`` + ``prefix.pgm`` in the ROS map_server format; returns both paths."""
        x0, y0 = self.origin_xy
        return write_ros_map(Path(prefix), self.render_pgm(), self.resolution_m, (x0, y0, 0.0),
                             comment=f"zagv world {self.name}")

    # ------------------------------------------------------------------ loading

    @classmethod
    def from_rectangles(cls, name: str, resolution_m: float, extent: list[float], free: list[list[float]],
                        obstacles: list[list[float]], glass: list[list[float]] | None = None, **kwargs: Any) -> World:
        x0, y0, x1, y1 = _check_rect(extent, "extent")
        cols = int(round((x1 - x0) / resolution_m))
        rows = int(round((y1 - y0) / resolution_m))
        solid = np.ones((rows, cols), dtype=bool)
        xs = x0 + (np.arange(cols) + 0.5) * resolution_m  # cell centres
        ys = y0 + (np.arange(rows) + 0.5) * resolution_m

        def mask(rect: list[float]) -> tuple[slice, slice]:
            a, b, c, d = _check_rect(rect, "rectangle")
            cs = np.searchsorted(xs, a), np.searchsorted(xs, c)
            rs = np.searchsorted(ys, b), np.searchsorted(ys, d)
            return slice(rs[0], rs[1]), slice(cs[0], cs[1])

        for r in free:
            solid[mask(r)] = False
        for r in obstacles:
            solid[mask(r)] = True
        glass_mask = None
        if glass:
            glass_mask = np.zeros_like(solid)
            for r in glass:
                glass_mask[mask(r)] = True
            solid |= glass_mask
        return cls(name=name, resolution_m=resolution_m, origin_xy=(x0, y0), solid=solid, glass=glass_mask, **kwargs)

    @classmethod
    def load_toml(cls, path: str | Path) -> World:
        path = Path(path)
        try:
            data = tomllib.loads(path.read_text())
        except (OSError, tomllib.TOMLDecodeError) as exc:
            raise WorldError(f"world file {path}: {exc}") from None
        return cls.from_dict(data, str(path))

    @classmethod
    def from_dict(cls, data: dict[str, Any], source: str = "world") -> World:
        try:
            goals = [Goal(str(g["id"]), _pose3(g["pose"])) for g in data.get("goals", [])]
            dynamic = {}
            for i, d in enumerate(data.get("dynamic_obstacles", [])):
                oid = str(d.get("id", f"dynamic{i + 1}"))
                dynamic[oid] = DynamicObstacle(oid, _check_rect(d["rect"], f"dynamic obstacle {oid}"),
                                               active=bool(d.get("active", False)),
                                               appear_at_s=d.get("appear_at_s"), vanish_at_s=d.get("vanish_at_s"))
            robots = [_robot_entry(r, k, source) for k, r in enumerate(data.get("robots", []), 1)]
            return cls.from_rectangles(
                str(data["name"]), float(data["resolution_m"]), data["extent_m"], data.get("free", []),
                data.get("obstacles", []), data.get("glass", []),
                start_pose=tuple(map(float, data.get("start_pose", (0.0, 0.0, 0.0)))),
                goals=goals, dynamic=dynamic, robots=robots)
        except KeyError as exc:
            raise WorldError(f"{source}: missing key {exc}") from None
        except (TypeError, ValueError) as exc:
            raise WorldError(f"{source}: {exc}") from None

    @classmethod
    def load_builtin(cls, name: str) -> World:
        names = builtin_worlds()
        if name not in names:
            raise WorldError(f"no built-in world {name!r}; available: {', '.join(names)}")
        text = resources.files("services.common").joinpath("worlds", f"{name}.toml").read_text()
        return cls.from_dict(tomllib.loads(text), f"built-in world {name}")

    @classmethod
    def load_map_yaml(cls, path: str | Path) -> World:
        """A ROS map_server map (YAML + PGM/PNG): occupied and unknown cells become solid.

        Honours ``negate``, ``occupied_thresh``/``free_thresh`` and ``mode`` (trinary/scale: a cell is free when
        its occupancy probability p = (255 - v)/255 (negate: v/255) is below ``free_thresh``; raw: v < 1 ... v is
        the occupancy 0..100 and free when < free_thresh*100). A yawed ``origin`` is resampled onto the axis-aligned
        raster that covers the rotated map (services.common.grid).
        """
        import yaml
        from PIL import Image

        path = Path(path)
        try:
            meta = yaml.safe_load(path.read_text())
            image_path = Path(meta["image"])
            if not image_path.is_absolute():
                image_path = path.parent / image_path
            resolution = float(meta["resolution"])
            origin = [float(v) for v in meta["origin"]]
            negate = int(meta.get("negate", 0))
            free_thresh = float(meta.get("free_thresh", 0.196))
            mode = str(meta.get("mode", "trinary"))
            img = np.asarray(Image.open(image_path).convert("L"), dtype=np.float64)
        except (OSError, KeyError, TypeError, ValueError, yaml.YAMLError) as exc:
            raise WorldError(f"map {path}: {type(exc).__name__}: {exc}") from None
        if len(origin) < 2:
            raise WorldError(f"map {path}: origin must be [x, y, yaw]")
        if mode == "raw":
            free = img < free_thresh * 100.0
        else:
            p = img / 255.0 if negate else (255.0 - img) / 255.0
            free = p < free_thresh
        solid = ~free[::-1]  # image row 0 is the top (max y)
        # a yawed origin: the raster is resampled onto the axis-aligned raster covering it (outside: solid)
        solid, x0, y0 = axis_aligned(solid, resolution, (origin[0], origin[1], origin[2] if len(origin) > 2 else 0.0),
                                     fill=True)
        return cls(name=path.stem, resolution_m=resolution, origin_xy=(x0, y0), solid=solid)


def builtin_worlds() -> list[str]:
    folder = resources.files("services.common").joinpath("worlds")
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".toml"))


def load_world(world: str = "", map_yaml: str = "") -> World:
    """A ROS map YAML when ``map_yaml`` is given, else the built-in world ``world``."""
    if map_yaml:
        return World.load_map_yaml(map_yaml)
    return World.load_builtin(world or "corridor")


def _robot_entry(raw: object, k: int, source: str) -> tuple[str, tuple[float, float, float]]:
    """One ``[[robots]]`` entry: ``id`` (a key chunk) and ``start`` [x, y, theta] (finite)."""
    if not isinstance(raw, dict) or set(raw) - {"id", "start"} or "id" not in raw or "start" not in raw:
        raise WorldError(f"{source}: robots[{k}] must have exactly `id` and `start` [x, y, theta], got {raw!r}")
    rid = str(raw["id"])
    if not rid or any(c in rid for c in "/*$?#"):
        raise WorldError(f"{source}: robots[{k}].id {rid!r} must be a non-empty key chunk without / * $ ? #")
    start = raw["start"]
    if not (isinstance(start, list) and len(start) == 3 and all(isinstance(v, int | float) for v in start)
            and all(math.isfinite(v) for v in start)):
        raise WorldError(f"{source}: robots[{k}].start must be finite [x, y, theta], got {start!r}")
    return rid, (float(start[0]), float(start[1]), float(start[2]))


def _pose3(values: list[float]) -> tuple[float, float, float]:
    """A goal pose [x_m, y_m, theta_rad] as floats (a wrong length fails here, naming the length)."""
    x, y, theta = (float(v) for v in values)
    return x, y, theta


def _check_rect(rect: Iterable[float], what: str) -> tuple[float, float, float, float]:
    try:
        vals = tuple(float(v) for v in rect)
    except (TypeError, ValueError):
        raise WorldError(f"{what}: expected [x_min, y_min, x_max, y_max] numbers, got {rect!r}") from None
    if len(vals) != 4 or not all(math.isfinite(v) for v in vals) or vals[0] >= vals[2] or vals[1] >= vals[3]:
        raise WorldError(f"{what}: expected finite [x_min, y_min, x_max, y_max] with min < max, got {rect!r}")
    return vals


def _boundary_tree(padded_solid: np.ndarray, origin_xy: tuple[float, float], res_m: float) -> cKDTree | None:
    """k-d tree of the centres (m) of the solid cells of a padded raster that have a free 4-neighbour."""
    free = ~padded_solid
    near_free = np.zeros_like(free)
    near_free[1:, :] |= free[:-1, :]
    near_free[:-1, :] |= free[1:, :]
    near_free[:, 1:] |= free[:, :-1]
    near_free[:, :-1] |= free[:, 1:]
    rows, cols = np.nonzero(padded_solid & near_free)
    if rows.size == 0:
        return None
    centres = np.column_stack((origin_xy[0] + (cols - 0.5) * res_m, origin_xy[1] + (rows - 0.5) * res_m))
    return cKDTree(centres)


def _distance_to_squares(tree: cKDTree | None, x: float, y: float, half_m: float) -> float:
    """Distance from (x, y) to the nearest square of half side ``half_m`` centred on a point of ``tree``."""
    if tree is None:
        return math.inf
    nearest_centre_m, _ = tree.query((x, y))
    candidates = tree.query_ball_point((x, y), float(nearest_centre_m) + half_m * (SQRT2 - 1.0) + 1e-9)
    c = tree.data[candidates]
    gap = np.maximum(np.abs(c - (x, y)) - half_m, 0.0)
    return float(np.sqrt((gap * gap).sum(axis=1)).min())


def _free_run_table(solid: np.ndarray) -> np.ndarray:
    """Signed extra free cells beyond the current one, per cell, for the four axis directions, flattened:
    [-x, +x, -y, +y] blocks of ``solid.size``; minus directions are negated so that ``face + table`` is the face
    where the free run ends (a solid cell gets 0)."""
    free = ~solid

    def run_towards_plus_col(f: np.ndarray) -> np.ndarray:
        out = np.zeros(f.shape, dtype=np.float32)
        acc = np.zeros(f.shape[0], dtype=np.float32)
        for c in range(f.shape[1] - 1, -1, -1):
            acc = np.where(f[:, c], acc + 1.0, 0.0).astype(np.float32)
            out[:, c] = acc
        return out

    x_plus = run_towards_plus_col(free)
    x_minus = run_towards_plus_col(free[:, ::-1])[:, ::-1]
    y_plus = run_towards_plus_col(free.T).T
    y_minus = run_towards_plus_col(free.T[:, ::-1])[:, ::-1].T
    extra = [-np.maximum(x_minus - 1.0, 0.0), np.maximum(x_plus - 1.0, 0.0),
             -np.maximum(y_minus - 1.0, 0.0), np.maximum(y_plus - 1.0, 0.0)]
    return np.concatenate([e.ravel() for e in extra]).astype(np.float32)


def _ray_rects(x: float, y: float, angles: np.ndarray, rects: np.ndarray, max_range_m: float) -> np.ndarray:
    """Slab test: distance along each beam to the nearest of the axis-aligned ``rects`` (max range if none)."""
    dx = np.cos(angles)[:, None]
    dy = np.sin(angles)[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        tx0 = (rects[None, :, 0] - x) / dx
        tx1 = (rects[None, :, 2] - x) / dx
        ty0 = (rects[None, :, 1] - y) / dy
        ty1 = (rects[None, :, 3] - y) / dy
        tmin = np.maximum(np.minimum(tx0, tx1), np.minimum(ty0, ty1))
        tmax = np.minimum(np.maximum(tx0, tx1), np.maximum(ty0, ty1))
    # a beam parallel to a slab gets +-inf there: unbounded inside the slab, a miss outside; 0/0 (nan) is a miss
    hit = tmax >= np.maximum(tmin, 0.0)
    t = np.where(hit, np.maximum(tmin, 0.0), np.inf)
    ranges: np.ndarray = np.minimum(t.min(axis=1), max_range_m)
    return ranges
