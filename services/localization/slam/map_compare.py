"""Occupied-cell agreement of two occupancy maps (a built map against the ground truth).

Cells are compared in the world frame: each occupied cell centre of one map is looked up in the other map. A built
occupied cell is a true positive when the ground truth has an occupied cell within ``tolerance_cells`` (Chebyshev
distance) of it; a ground-truth occupied cell is recalled when the built map has one within the same tolerance.
``precision = matched built / built``, ``recall = matched truth / truth``, ``F1 = 2 P R / (P + R)``.
Only ground-truth cells inside ``region`` (x_min, y_min, x_max, y_max in m, default: everywhere) count for recall,
so a partly explored world can be scored on the part that was explored; with ``built_free`` (the built map's free
cells) only ground-truth cells within ``observed_cells`` of a built free cell count for recall (walls the lidar could
not have seen, such as the far side of a cabinet, are not held against the map). ``surface`` turns a solid
ground-truth rendering (walls are filled blocks) into its visible boundary: occupied cells next to a free cell.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage


@dataclass(frozen=True)
class MapAgreement:
    precision: float
    recall: float
    f1: float
    built_occupied: int
    truth_occupied: int
    offset_xy_m: tuple[float, float]


def surface(occupied: np.ndarray, free: np.ndarray) -> np.ndarray:
    """Occupied cells with a free 8-neighbour."""
    bordering: np.ndarray = occupied & ndimage.binary_dilation(free, np.ones((3, 3), bool))
    return bordering


def occupied_centres(occupied: np.ndarray, resolution_m: float, origin_xy_m: tuple[float, float]) -> np.ndarray:
    """World (x, y) of the centres of the occupied cells of ``occupied[row, col]`` (row 0 at the origin's y)."""
    rows, cols = np.nonzero(occupied)
    return np.stack([origin_xy_m[0] + (cols + 0.5) * resolution_m, origin_xy_m[1] + (rows + 0.5) * resolution_m],
                    axis=1)


def _hits(points: np.ndarray, occupied: np.ndarray, resolution_m: float, origin_xy_m: tuple[float, float],
          tolerance_cells: int) -> np.ndarray:
    """Which world points fall on (or within ``tolerance_cells`` of) an occupied cell of ``occupied``."""
    grown = ndimage.binary_dilation(occupied, np.ones((2 * tolerance_cells + 1,) * 2, bool)) \
        if tolerance_cells > 0 else occupied
    col = np.floor((points[:, 0] - origin_xy_m[0]) / resolution_m).astype(np.intp)
    row = np.floor((points[:, 1] - origin_xy_m[1]) / resolution_m).astype(np.intp)
    inside = (row >= 0) & (col >= 0) & (row < occupied.shape[0]) & (col < occupied.shape[1])
    out = np.zeros(len(points), bool)
    out[inside] = grown[row[inside], col[inside]]
    return out


def occupied_f1(built: np.ndarray, built_resolution_m: float, built_origin_xy_m: tuple[float, float],
                truth: np.ndarray, truth_resolution_m: float, truth_origin_xy_m: tuple[float, float], *,
                tolerance_cells: int = 1, region: tuple[float, float, float, float] | None = None,
                offset_xy_m: tuple[float, float] = (0.0, 0.0), built_free: np.ndarray | None = None,
                observed_cells: int = 2) -> MapAgreement:
    """Precision, recall and F1 of the occupied cells (boolean grids, row 0 at the origin); the built map is shifted
    by ``offset_xy_m`` before comparing."""
    b = occupied_centres(built, built_resolution_m, built_origin_xy_m) + np.asarray(offset_xy_m)
    t = occupied_centres(truth, truth_resolution_m, truth_origin_xy_m)
    if region is not None:
        x0, y0, x1, y1 = region
        b = b[(b[:, 0] >= x0) & (b[:, 0] <= x1) & (b[:, 1] >= y0) & (b[:, 1] <= y1)]
        t = t[(t[:, 0] >= x0) & (t[:, 0] <= x1) & (t[:, 1] >= y0) & (t[:, 1] <= y1)]
    shifted_origin = (built_origin_xy_m[0] + offset_xy_m[0], built_origin_xy_m[1] + offset_xy_m[1])
    if built_free is not None:
        t = t[_hits(t, built_free, built_resolution_m, shifted_origin, observed_cells)]
    precision = float(_hits(b, truth, truth_resolution_m, truth_origin_xy_m, tolerance_cells).mean()) if len(b) else 0.0
    recall = float(_hits(t, built, built_resolution_m, shifted_origin, tolerance_cells).mean()) if len(t) else 0.0
    f1 = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    return MapAgreement(precision, recall, f1, len(b), len(t), (float(offset_xy_m[0]), float(offset_xy_m[1])))


def best_aligned_f1(built: np.ndarray, built_resolution_m: float, built_origin_xy_m: tuple[float, float],
                    truth: np.ndarray, truth_resolution_m: float, truth_origin_xy_m: tuple[float, float], *,
                    search_cells: int = 2, tolerance_cells: int = 1,
                    region: tuple[float, float, float, float] | None = None,
                    built_free: np.ndarray | None = None) -> MapAgreement:
    """``occupied_f1`` at the best translation within ±``search_cells`` built cells (a small refinement of an
    alignment already given by the shared start pose); among equal scores the smallest shift wins."""
    best: MapAgreement | None = None
    shifts = [(i, j) for i in range(-search_cells, search_cells + 1) for j in range(-search_cells, search_cells + 1)]
    for i, j in sorted(shifts, key=lambda s: s[0] ** 2 + s[1] ** 2):
        dx, dy = i * built_resolution_m, j * built_resolution_m
        r = occupied_f1(built, built_resolution_m, built_origin_xy_m, truth, truth_resolution_m, truth_origin_xy_m,
                        tolerance_cells=tolerance_cells, region=region, offset_xy_m=(float(dx), float(dy)),
                        built_free=built_free)
        if best is None or r.f1 > best.f1:
            best = r
    assert best is not None
    return best
