"""Occupancy maps in the ROS map_server format: a YAML file plus a PGM/PNG image (I/O only here, no networking).

YAML keys (map_server / Nav2 map_io): ``image`` (path relative to the YAML), ``resolution`` (m/pixel), ``origin``
``[x, y, yaw]`` (pose of the lower-left pixel's outer corner in the map frame), ``negate`` (0/1), ``occupied_thresh``,
``free_thresh`` and ``mode`` (``trinary`` when absent, ``scale`` or ``raw``).

Pixel -> occupancy probability: ``p = (255 - gray) / 255`` (darker is more occupied), ``p = gray / 255`` with
``negate``; colour images use the mean of their colour channels. Modes, with Nav2's inclusive thresholds:
- trinary: ``p >= occupied_thresh`` -> 100, ``p <= free_thresh`` -> 0, else -1 (unknown);
- scale: as trinary at the ends, in between ``round(100 (p - free) / (occ - free))``; any pixel that is not fully
  opaque (alpha < 255) is unknown;
- raw: the (negated) gray value itself, when in [0, 100], else unknown.

Files are read with limits: the YAML must be a regular file of at most ``MAX_YAML_BYTES``, the image a regular file
of at most ``MAX_IMAGE_BYTES`` and ``MAX_IMAGE_CELLS`` pixels, so a device (``/dev/zero``), a FIFO or a huge file is
refused at once. Error messages name the file and the problem but never quote the file's content.

Image row 0 is the map's top (max y); :class:`OccupancyMap` rows start at the origin (min y), as OccupancyGrid does.
Saving writes a trinary PGM (254 free, 0 occupied, 205 unknown) with ``occupied_thresh: 0.65``, ``free_thresh:
0.196``, ``negate: 0`` like map_saver.
"""

from __future__ import annotations

import io
import math
import os
import stat
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml
from PIL import Image, UnidentifiedImageError

from proto.messages import OccupancyGrid, Pose2D
from services.common.ros_map import FREE_THRESH, OCCUPIED_THRESH, trinary_pixels, write_ros_map
from services.common.se2 import rotate

FREE, OCCUPIED, UNKNOWN = 0, 100, -1
SAVE_OCCUPIED_THRESH, SAVE_FREE_THRESH = OCCUPIED_THRESH, FREE_THRESH
MODES = ("trinary", "scale", "raw")
REQUIRED_KEYS = ("image", "resolution", "origin")
MAX_YAML_BYTES = 64 * 1024
MAX_IMAGE_BYTES = 256 * 1024 * 1024
MAX_IMAGE_CELLS = 8000 * 8000


class MapError(ValueError):
    """A map that cannot be loaded or saved; the message names the file and what is wrong with it."""


@dataclass
class OccupancyMap:
    """An occupancy grid: ``data[row, col]`` int8 (-1 unknown, 0 free .. 100 occupied), row 0 at the origin.

    ``origin`` is (x [m], y [m], yaw [rad]) of cell (0, 0)'s outer corner in the map frame; ``resolution`` m/cell.
    """

    data: np.ndarray
    resolution: float
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @property
    def height(self) -> int:
        return int(self.data.shape[0])

    @property
    def width(self) -> int:
        return int(self.data.shape[1])

    def counts(self) -> dict[str, int]:
        """Cells that are free (0), occupied (>= 65, as the saver's threshold) and unknown (-1); the rest 'other'."""
        d = self.data
        free = int(np.count_nonzero(d == FREE))
        unknown = int(np.count_nonzero(d == UNKNOWN))
        occupied = int(np.count_nonzero(d >= round(SAVE_OCCUPIED_THRESH * 100)))
        return {"free": free, "occupied": occupied, "unknown": unknown,
                "other": int(d.size) - free - unknown - occupied}

    def to_msg(self, stamp: float = 0.0, frame: str = "map") -> OccupancyGrid:
        ox, oy, oyaw = self.origin
        return OccupancyGrid(stamp=stamp, frame=frame, resolution=self.resolution, width=self.width,
                             height=self.height, origin=Pose2D(x=ox, y=oy, theta=oyaw),
                             data=np.ascontiguousarray(self.data, dtype=np.int8).tobytes())

    @classmethod
    def from_msg(cls, msg: OccupancyGrid) -> OccupancyMap:
        if msg.width <= 0 or msg.height <= 0 or len(msg.data) != msg.width * msg.height:
            raise MapError(f"OccupancyGrid: {len(msg.data)} cells do not fill {msg.width} x {msg.height}")
        data = np.frombuffer(msg.data, dtype=np.int8).reshape(msg.height, msg.width).copy()
        return cls(data, float(msg.resolution), (msg.origin.x, msg.origin.y, msg.origin.theta))

    def world_to_cell(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Map-frame points (m) -> integer (col, row), honouring the origin's yaw; may lie outside the grid."""
        ox, oy, oyaw = self.origin
        bx, by = rotate(-oyaw, np.asarray(x) - ox, np.asarray(y) - oy)
        gx, gy = bx / self.resolution, by / self.resolution
        return np.floor(gx).astype(np.int64), np.floor(gy).astype(np.int64)

    def cell_to_world(self, col: np.ndarray, row: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Centres of cells (col, row) in the map frame (m)."""
        ox, oy, oyaw = self.origin
        wx, wy = rotate(oyaw, (np.asarray(col) + 0.5) * self.resolution, (np.asarray(row) + 0.5) * self.resolution)
        return ox + wx, oy + wy


def _shown(value: object) -> str:
    """A value from a file as an error shows it: numbers as they are, anything else only by its type."""
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return repr(value)
    return f"a {type(value).__name__}"


def _number(meta: dict, key: str, path: Path) -> float:
    value = meta[key]
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise MapError(f"map {path}: `{key}` must be a finite number, got {_shown(value)}")
    return float(value)


def read_limited(path: Path, limit_bytes: int, what: str) -> bytes:
    """The bytes of ``path`` when it is a regular file of at most ``limit_bytes``; MapError otherwise (a device,
    FIFO or folder is refused without reading from it)."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except OSError as exc:
        raise MapError(f"{what} {path}: cannot read: {exc.strerror or exc}") from None
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise MapError(f"{what} {path}: not a regular file")
        if info.st_size > limit_bytes:
            raise MapError(f"{what} {path}: {info.st_size} bytes, more than the {limit_bytes} allowed")
        chunks, size = [], 0
        while size <= limit_bytes and (chunk := os.read(fd, min(1 << 20, limit_bytes + 1 - size))):
            chunks.append(chunk)
            size += len(chunk)
        data = b"".join(chunks)
    except OSError as exc:
        raise MapError(f"{what} {path}: cannot read: {exc.strerror or exc}") from None
    finally:
        os.close(fd)
    if len(data) > limit_bytes:
        raise MapError(f"{what} {path}: more than the {limit_bytes} bytes allowed")
    return data


def read_map_yaml(path: str | Path) -> dict:
    """Parse and validate a map YAML; returns the keys with defaults filled in and ``image`` made absolute."""
    path = Path(path)
    raw = read_limited(path, MAX_YAML_BYTES, "map")
    try:
        meta = yaml.safe_load(raw.decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise MapError(f"map {path}: not UTF-8 text (byte {exc.start})") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        raise MapError(f"map {path}: not a map YAML (syntax error{where})") from None
    if not isinstance(meta, dict):
        raise MapError(f"map {path}: expected a mapping of keys, got {_shown(meta)}")
    missing = [k for k in REQUIRED_KEYS if k not in meta]
    if missing:
        raise MapError(f"map {path}: missing key(s) {', '.join(missing)}")
    if not isinstance(meta["image"], str) or not meta["image"]:
        raise MapError(f"map {path}: `image` must be a file name, got {_shown(meta['image'])}")
    resolution = _number(meta, "resolution", path)
    if resolution <= 0:
        raise MapError(f"map {path}: `resolution` must be > 0, got {resolution}")
    origin = meta["origin"]
    if not isinstance(origin, (list, tuple)) or len(origin) != 3:
        raise MapError(f"map {path}: `origin` must be [x, y, yaw] (3 numbers), got {_shown(origin)}")
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in origin):
        raise MapError(f"map {path}: `origin` must hold finite numbers, got [{', '.join(map(_shown, origin))}]")
    mode = meta.get("mode", "trinary")
    if mode not in MODES:
        raise MapError(f"map {path}: `mode` must be one of {', '.join(MODES)}, got {_shown(mode)}")
    negate = meta.get("negate", 0)
    if negate not in (0, 1, True, False):
        raise MapError(f"map {path}: `negate` must be 0 or 1, got {_shown(negate)}")
    out = {"image": str((path.parent / meta["image"]).resolve()), "resolution": resolution,
           "origin": tuple(float(v) for v in origin), "mode": mode, "negate": bool(negate)}
    for key, default in (("occupied_thresh", SAVE_OCCUPIED_THRESH), ("free_thresh", SAVE_FREE_THRESH)):
        out[key] = _number(meta, key, path) if key in meta else default
        if not 0.0 <= out[key] <= 1.0:
            raise MapError(f"map {path}: `{key}` must lie in [0, 1], got {out[key]}")
    if out["free_thresh"] > out["occupied_thresh"]:
        raise MapError(f"map {path}: free_thresh {out['free_thresh']} exceeds occupied_thresh {out['occupied_thresh']}")
    return out


def _read_pixels(image_path: Path, yaml_path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Gray levels (mean of the colour channels, float 0..255) and the alpha channel (or None), image row order."""
    if not image_path.exists():
        raise MapError(f"map {yaml_path}: image {image_path} does not exist")
    raw = read_limited(image_path, MAX_IMAGE_BYTES, f"map {yaml_path}: image")
    try:
        with Image.open(io.BytesIO(raw)) as opened:
            img: Image.Image = opened
            if img.width * img.height > MAX_IMAGE_CELLS:
                raise MapError(f"map {yaml_path}: image {image_path} has {img.width} x {img.height} pixels, more "
                               f"than the {MAX_IMAGE_CELLS} allowed")
            img.load()
            if img.mode in ("P", "PA"):
                img = img.convert("RGBA")
            elif img.mode in ("I", "I;16", "I;16B", "I;16L", "F"):
                arr = np.asarray(img, dtype=np.float64)
                scale = 255.0 / 65535.0 if img.mode.startswith("I;16") or arr.max(initial=0) > 255 else 1.0
                return arr * scale, None
            elif img.mode not in ("L", "LA", "RGB", "RGBA"):
                img = img.convert("RGBA" if "A" in img.mode else "RGB")
            arr = np.asarray(img)
    except MapError:
        raise
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as exc:
        raise MapError(f"map {yaml_path}: cannot read image {image_path}: {exc}") from None
    if arr.ndim == 2:
        return arr.astype(np.float64), None
    colour = arr[..., :3] if arr.shape[2] >= 3 else arr[..., :1]
    alpha = arr[..., -1] if arr.shape[2] in (2, 4) else None
    return colour.mean(axis=2, dtype=np.float64), alpha


def pixels_to_cells(gray: np.ndarray, alpha: np.ndarray | None, *, mode: str, negate: bool,
                    occupied_thresh: float, free_thresh: float) -> np.ndarray:
    """Apply the map_server conversion to gray levels (image row order kept); returns int8 cells."""
    gray = np.rint(gray)
    if mode == "raw":
        value = 255.0 - gray if negate else gray
        return np.where((value >= 0) & (value <= 100), value, UNKNOWN).astype(np.int8)
    p = gray / 255.0 if negate else (255.0 - gray) / 255.0
    cells = np.full(gray.shape, UNKNOWN, dtype=np.int8)
    if mode == "scale":
        span = max(occupied_thresh - free_thresh, 1e-9)
        graded = np.rint(100.0 * (p - free_thresh) / span).clip(0, 100)
        cells[:] = graded.astype(np.int8)
    cells[p >= occupied_thresh] = OCCUPIED
    cells[p <= free_thresh] = FREE
    if mode == "scale" and alpha is not None:
        cells[alpha < 255] = UNKNOWN
    return cells


def load_map(yaml_path: str | Path) -> OccupancyMap:
    """Load a map_server YAML and its image into an :class:`OccupancyMap` (rows flipped to start at the origin)."""
    yaml_path = Path(yaml_path)
    meta = read_map_yaml(yaml_path)
    gray, alpha = _read_pixels(Path(meta["image"]), yaml_path)
    if gray.size == 0:
        raise MapError(f"map {yaml_path}: image {meta['image']} is empty")
    cells = pixels_to_cells(gray, alpha, mode=meta["mode"], negate=meta["negate"],
                            occupied_thresh=meta["occupied_thresh"], free_thresh=meta["free_thresh"])
    return OccupancyMap(np.ascontiguousarray(cells[::-1]), meta["resolution"], meta["origin"])


def coarsen(grid: OccupancyMap, k: int) -> OccupancyMap:
    """The map re-rastered onto cells k times as large, as a mapper with that cell would have drawn it. Each k x k
    block becomes: occupied when any of its cells is occupied (a thin wall stays a wall), else free when at least
    half of it is known and at least half of its known cells are free, else unknown. A partial block at the far
    edges is padded with unknown; the origin is kept."""
    if not isinstance(k, int) or k < 1:
        raise MapError(f"coarsen: the factor must be a whole number >= 1, got {k!r}")
    if k == 1:
        return OccupancyMap(grid.data.copy(), grid.resolution, grid.origin)
    rows, cols = -(-grid.height // k), -(-grid.width // k)
    padded = np.full((rows * k, cols * k), UNKNOWN, dtype=np.int8)
    padded[:grid.height, :grid.width] = grid.data
    blocks = padded.reshape(rows, k, cols, k).swapaxes(1, 2).reshape(rows, cols, k * k)
    occupied = (blocks >= OCCUPIED_THRESH * 100.0).any(axis=2)
    known = (blocks >= 0).sum(axis=2)
    free = ((blocks >= 0) & (blocks <= FREE_THRESH * 100.0)).sum(axis=2)
    out = np.full((rows, cols), UNKNOWN, dtype=np.int8)
    out[(2 * known >= k * k) & (2 * free >= known)] = FREE
    out[occupied] = OCCUPIED
    return OccupancyMap(out, k * grid.resolution, grid.origin)


def save_map(grid: OccupancyMap, base: str | Path, *, free_thresh: float = SAVE_FREE_THRESH,
             occupied_thresh: float = SAVE_OCCUPIED_THRESH) -> tuple[Path, Path]:
    """Write ``<base>.yaml`` + ``<base>.pgm`` (trinary) like map_saver; returns both paths.

    A cell is written free (254) when 0 <= value <= 100 * free_thresh, occupied (0) when value >= 100 *
    occupied_thresh, unknown (205) otherwise (``services.common.ros_map``).
    """
    pixels = trinary_pixels(grid.data, free_thresh=free_thresh, occupied_thresh=occupied_thresh)
    try:
        ox, oy, oyaw = grid.origin
        return write_ros_map(base, pixels[::-1], grid.resolution, (float(ox), float(oy), float(oyaw)),
                             comment="zagv map")
    except OSError as exc:
        raise MapError(f"map {base}: cannot write: {exc.strerror or exc}") from None
