"""Log-odds occupancy grid rendered from scans at known poses.

Each scan adds ``log_odds_free`` to every cell its beams cross (sampled every half cell, the end cell
excluded) and ``log_odds_occupied`` to the cell of each hit, once per cell per scan. Cells are read as
P(occ) = 1 - 1 / (1 + exp(l)) and exported in the ROS map_server trinary convention: occupied 0,
free 254, unknown 205 (image rows top = largest y).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.common.se2 import transform_points

PGM_OCCUPIED = 0
PGM_FREE = 254
PGM_UNKNOWN = 205


@dataclass
class OccupancyGrid:
    """``log_odds[iy, ix]`` over cells of ``resolution_m`` whose grid lower-left corner is ``origin_xy_m``."""

    log_odds: np.ndarray
    origin_xy_m: np.ndarray
    resolution_m: float
    log_odds_occupied: float = 0.9
    log_odds_free: float = -0.4
    clamp: float = 10.0

    @classmethod
    def covering(cls, lower_xy_m: np.ndarray, upper_xy_m: np.ndarray, resolution_m: float,
                 margin_m: float = 1.0) -> OccupancyGrid:
        lo = np.asarray(lower_xy_m, float) - margin_m
        hi = np.asarray(upper_xy_m, float) + margin_m
        shape = np.ceil((hi - lo) / resolution_m).astype(int) + 1
        return cls(np.zeros((shape[1], shape[0]), np.float32), lo, float(resolution_m))

    def _cells(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ix = np.floor((points[:, 0] - self.origin_xy_m[0]) / self.resolution_m).astype(np.intp)
        iy = np.floor((points[:, 1] - self.origin_xy_m[1]) / self.resolution_m).astype(np.intp)
        return ix, iy

    def _flat(self, ix: np.ndarray, iy: np.ndarray) -> np.ndarray:
        h, w = self.log_odds.shape
        ok = (ix >= 0) & (iy >= 0) & (ix < w) & (iy < h)
        flat: np.ndarray = iy[ok] * w + ix[ok]
        return flat

    def insert_scan(self, pose: np.ndarray, sensor_origin_xy_m: np.ndarray, points: np.ndarray) -> None:
        """Integrate hits ``points`` (N, 2, robot frame) seen from ``sensor_origin_xy_m`` (robot frame) by the
        robot at ``pose`` (x, y, theta)."""
        if len(points) == 0:
            return
        origin = transform_points(pose, np.asarray(sensor_origin_xy_m, float).reshape(1, 2))[0]
        hits = transform_points(pose, points)
        delta = hits - origin
        length = np.hypot(delta[:, 0], delta[:, 1])
        step = 0.5 * self.resolution_m
        n_samples = np.maximum((length / step).astype(np.intp), 0)
        total = int(n_samples.sum())
        beam = np.repeat(np.arange(len(hits)), n_samples)
        starts = np.cumsum(n_samples) - n_samples
        k = np.arange(total) - np.repeat(starts, n_samples)
        frac = (k * step / np.maximum(length[beam], 1e-9))[:, None]
        samples = origin + frac * delta[beam]
        free_flat = np.unique(self._flat(*self._cells(samples)))
        hit_flat = np.unique(self._flat(*self._cells(hits)))
        free_flat = np.setdiff1d(free_flat, hit_flat, assume_unique=True)
        flat = self.log_odds.ravel()
        flat[free_flat] += self.log_odds_free
        flat[hit_flat] += self.log_odds_occupied
        np.clip(flat, -self.clamp, self.clamp, out=flat)

    def probability(self) -> np.ndarray:
        probability: np.ndarray = 1.0 - 1.0 / (1.0 + np.exp(self.log_odds))
        return probability

    def trinary_image(self, occupied_thresh: float = 0.65, free_thresh: float = 0.196) -> np.ndarray:
        """uint8 image (rows top = max y): 0 occupied, 254 free, 205 unknown."""
        p = self.probability()
        image = np.full(p.shape, PGM_UNKNOWN, np.uint8)
        image[p > occupied_thresh] = PGM_OCCUPIED
        image[p < free_thresh] = PGM_FREE
        return image[::-1].copy()
