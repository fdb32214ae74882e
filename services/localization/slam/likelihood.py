"""Smooth likelihood grids for scan matching, at several resolutions.

A level rasterises the map's hit points at ``resolution_m`` and blurs them with a Gaussian of ``sigma_cells``;
the result is scaled so that a straight wall of hits peaks at 1 and clipped to [0, 1], i.e. near a wall
M(d) ≈ exp(-d² / 2σ²) with d the distance to the wall. Values and gradients are read by bilinear
interpolation (Kohlbrecher et al. 2011, Hector mapping), which gives sub-cell accuracy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage


@dataclass
class LikelihoodGrid:
    """One resolution level: ``field[iy, ix]`` over cells whose lower-left corner is ``origin_xy_m``."""

    field: np.ndarray
    origin_xy_m: np.ndarray
    resolution_m: float

    @classmethod
    def from_points(cls, points_xy_m: np.ndarray, resolution_m: float, *, sigma_cells: float = 1.5,
                    margin_m: float = 1.0) -> LikelihoodGrid:
        """Grid covering ``points_xy_m`` (N, 2) plus ``margin_m`` on each side."""
        if len(points_xy_m) == 0:
            raise ValueError("cannot build a likelihood grid from zero points")
        lo = points_xy_m.min(axis=0) - margin_m
        hi = points_xy_m.max(axis=0) + margin_m
        shape = np.ceil((hi - lo) / resolution_m).astype(int) + 1
        ix = ((points_xy_m[:, 0] - lo[0]) / resolution_m).astype(np.intp)
        iy = ((points_xy_m[:, 1] - lo[1]) / resolution_m).astype(np.intp)
        hits = np.zeros((shape[1], shape[0]), np.float32)
        hits[iy, ix] = 1.0
        blurred = ndimage.gaussian_filter(hits, sigma_cells, truncate=3.0)
        field = np.minimum(blurred * (np.sqrt(2.0 * np.pi) * sigma_cells), 1.0).astype(np.float32)
        return cls(field, lo.astype(float), float(resolution_m))

    def value_and_gradient(self, points_xy_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Bilinear M(p) and ∇M(p) (per metre) at points (N, 2); zero outside the grid.

        Cell centres sit at origin + (i + 0.5) * resolution.
        """
        f = self.field
        u = (points_xy_m[:, 0] - self.origin_xy_m[0]) / self.resolution_m - 0.5
        v = (points_xy_m[:, 1] - self.origin_xy_m[1]) / self.resolution_m - 0.5
        x0 = np.floor(u).astype(np.intp)
        y0 = np.floor(v).astype(np.intp)
        ok = (x0 >= 0) & (y0 >= 0) & (x0 < f.shape[1] - 1) & (y0 < f.shape[0] - 1)
        x0 = np.where(ok, x0, 0)
        y0 = np.where(ok, y0, 0)
        fu = u - x0
        fv = v - y0
        m00 = f[y0, x0]
        m10 = f[y0, x0 + 1]
        m01 = f[y0 + 1, x0]
        m11 = f[y0 + 1, x0 + 1]
        value = (1 - fv) * ((1 - fu) * m00 + fu * m10) + fv * ((1 - fu) * m01 + fu * m11)
        du = (1 - fv) * (m10 - m00) + fv * (m11 - m01)
        dv = (1 - fu) * (m01 - m00) + fu * (m11 - m10)
        grad = np.stack([du, dv], axis=1) / self.resolution_m
        value = np.where(ok, value, 0.0)
        grad[~ok] = 0.0
        return value, grad

    def nearest_values(self, points_xy_m: np.ndarray) -> np.ndarray:
        """M at the cell containing each point (0 outside); cheap, for scoring."""
        ix = np.floor((points_xy_m[:, 0] - self.origin_xy_m[0]) / self.resolution_m).astype(np.intp)
        iy = np.floor((points_xy_m[:, 1] - self.origin_xy_m[1]) / self.resolution_m).astype(np.intp)
        ok = (ix >= 0) & (iy >= 0) & (ix < self.field.shape[1]) & (iy < self.field.shape[0])
        out = np.zeros(len(points_xy_m), np.float32)
        out[ok] = self.field[iy[ok], ix[ok]]
        return out


@dataclass
class MultiResolutionGrid:
    """Levels from fine to coarse, each twice the previous cell size (``levels[0]`` is the finest)."""

    levels: list[LikelihoodGrid]

    @classmethod
    def from_points(cls, points_xy_m: np.ndarray, finest_resolution_m: float, n_levels: int = 3, *,
                    sigma_cells: float = 1.5) -> MultiResolutionGrid:
        levels = [LikelihoodGrid.from_points(points_xy_m, finest_resolution_m * 2**k, sigma_cells=sigma_cells)
                  for k in range(n_levels)]
        return cls(levels)
