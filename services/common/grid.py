"""Occupancy rasters whose origin carries a yaw, resampled onto an axis-aligned raster.

A ROS map's ``origin`` is (x, y, yaw) of cell (0, 0)'s outer corner; with yaw != 0 cell (row r, column c) has its
centre at ``origin + R(yaw) @ ((c + 0.5) res, (r + 0.5) res)``. Costmaps and the simulator's raster are axis
aligned, so such a map is resampled (nearest cell, same resolution) onto the axis-aligned raster that covers its
rotated extent; cells of the new raster that fall outside the source grid take ``fill``.
"""

from __future__ import annotations

import math

import numpy as np

from proto.messages import OccupancyGrid
from services.common.se2 import rotate

#: yaw below this (rad) is treated as axis aligned
YAW_EPS_RAD = 1e-9


def axis_aligned(data: np.ndarray, resolution: float, origin: tuple[float, float, float], fill: int | bool
                 ) -> tuple[np.ndarray, float, float]:
    """(raster, origin_x, origin_y) of ``data`` (rows from the origin) resampled onto an axis-aligned raster."""
    ox, oy, yaw = (float(origin[0]), float(origin[1]), float(origin[2]) if len(origin) > 2 else 0.0)
    if abs(yaw) < YAW_EPS_RAD:
        return data, ox, oy
    h, w = data.shape
    corners = np.array([[0.0, 0.0], [w, 0.0], [0.0, h], [w, h]]) * resolution
    cx, cy = rotate(yaw, corners[:, 0], corners[:, 1])
    xs, ys = ox + cx, oy + cy
    x0, y0 = float(xs.min()), float(ys.min())
    cols = int(math.ceil((xs.max() - x0) / resolution - 1e-6))
    rows = int(math.ceil((ys.max() - y0) / resolution - 1e-6))
    out = np.full((rows, cols), fill, dtype=data.dtype)
    jj, ii = np.meshgrid(np.arange(cols), np.arange(rows))
    dx = x0 + (jj + 0.5) * resolution - ox
    dy = y0 + (ii + 0.5) * resolution - oy
    bx, by = rotate(-yaw, dx, dy)
    src_c = np.floor(bx / resolution).astype(np.int64)
    src_r = np.floor(by / resolution).astype(np.int64)
    ok = (src_c >= 0) & (src_c < w) & (src_r >= 0) & (src_r < h)
    out[ok] = data[src_r[ok], src_c[ok]]
    return out, x0, y0


def grid_png(grid: OccupancyGrid) -> bytes:
    """An OccupancyGrid as a greyscale PNG, north up: row 0 of the image is the grid's last row (largest y).

    Free (0) is white, occupied (100) black, unknown (-1) grey, values in between shaded linearly.
    """
    import io

    from PIL import Image

    cells = np.frombuffer(grid.data, dtype="<i1")
    if grid.width <= 0 or grid.height <= 0 or len(cells) != grid.width * grid.height:
        raise ValueError(f"map has {len(cells)} cells for {grid.width}x{grid.height}")
    cells = cells.reshape(grid.height, grid.width)
    grey = np.where(cells < 0, 205, 254 - (np.clip(cells, 0, 100).astype(np.int32) * 254) // 100).astype(np.uint8)
    buf = io.BytesIO()
    Image.fromarray(grey[::-1], mode="L").save(buf, format="PNG", optimize=False)
    return buf.getvalue()
