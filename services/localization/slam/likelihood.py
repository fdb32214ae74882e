"""Smooth likelihood grids for scan matching, at several resolutions.

A level splats the map's hit points at ``resolution_m`` and blurs them with a Gaussian of ``sigma_cells``;
the result is scaled so that a straight wall of hits peaks at 1 and clipped to [0, 1], i.e. near a wall
M(d) ≈ exp(-d² / 2σ²) with d the distance to the wall. Values and gradients come from a local quadratic fit
(see ``value_and_gradient``), which gives sub-cell accuracy as Hector mapping's bilinear interpolation
(Kohlbrecher et al. 2011) intends, without its flat tops between cell centres.

Known bias: the blur sums, so the field peaks where hits are dense. A wall seen at a grazing angle is sampled
ever more sparsely with range, its ridge falls off away from the viewpoint, and a scan sliding along it is drawn
back towards the keyframes that saw it: matches come out short along corridors. On the corrected infinite-corridor
log (1° beams, 1 m steps), each scan refined against the one before it from the reference's relative pose came
out 0.93 % short over the pairs that fix both directions (3.7 % at 3 cells); point-to-line ICP of the same pairs
gives 0.02 %. In the mapper, with 20 keyframes per submap and exact odometry, keyframe edges run 0.06-0.9 % short of
the reference on ten of the twelve corrected logs. Two replacements were measured on every log (seed 1) and not
kept. The distance-to-nearest-hit field (exp(-d²/2σ²), every hit a peak of 1) improved six corrected logs
(edmonton 0.42 -> 0.32 m, acapulco 0.12 -> 0.09, aces 0.10 -> 0.07), but orebro went 0.064 -> 0.17 m and
freiburg-campus 0.24 -> 0.36 (sparse hits weigh as much as walls), ACES' relation error rose 0.037 -> 0.040 m,
and the synthetic corridor of ``tests/test_slam_scale.py`` mapped 1 % long: with the density slope gone, the pull
of points the submap never saw (``visibility.py``) is no longer offset. With that test taking the shortest ray
per bearing (a jamb hides the recess behind it) and applied to every match, the corridor held (+0.03 / +0.16 %),
edmonton went to 0.19 m and seattle to 0.036, but csail 0.12 -> 0.17, orebro 0.16 and freiburg-campus 0.41, and
20 closures on freiburg-079 disagreed with its reference (4 before). Surfaces filled in between adjacent hits
(adaptive breakpoint detector) lost on the relations logs (FR079 0.049 -> 0.052 m, MIT CSAIL degraded 0.035 ->
0.043) and on freiburg-campus (0.24 -> 0.76 m).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.common.gridops import quadratic_sample


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
        # bilinear splat onto cell centres, keeping the largest weight per cell: a wall's profile peaks at its
        # true position (sub-cell), and overlapping scans do not saturate it
        u = (points_xy_m[:, 0] - lo[0]) / resolution_m - 0.5
        v = (points_xy_m[:, 1] - lo[1]) / resolution_m - 0.5
        x0 = np.floor(u).astype(np.intp)
        y0 = np.floor(v).astype(np.intp)
        fu = u - x0
        fv = v - y0
        cols = np.concatenate([x0, x0 + 1, x0, x0 + 1])
        rows = np.concatenate([y0, y0, y0 + 1, y0 + 1])
        weights = np.concatenate([(1 - fu) * (1 - fv), fu * (1 - fv), (1 - fu) * fv, fu * fv]).astype(np.float32)
        hits = np.zeros((shape[1], shape[0]), np.float32)
        np.maximum.at(hits.ravel(), rows * shape[0] + cols, weights)
        from scipy import ndimage  # here: mapping mode only; importing it costs about 30 MB resident

        blurred = ndimage.gaussian_filter(hits, sigma_cells, truncate=3.0)
        field = np.minimum(blurred * (np.sqrt(2.0 * np.pi) * sigma_cells), 1.0).astype(np.float32)
        return cls(field, lo.astype(float), float(resolution_m))

    def value_and_gradient(self, points_xy_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """M(p) and ∇M(p) (per metre) at points (N, 2); zero outside the grid.

        Second-order Taylor expansion about the nearest cell centre c (centres at origin + (i + 0.5) * res):
        M(c + δ) ≈ M_c + gᵀδ + ½ δᵀHδ with g, H from central differences of the 3x3 neighbourhood. Unlike
        bilinear interpolation, this keeps a peak between two cell centres peaked, so a wall's position is
        found to a small fraction of a cell (``services.common.gridops.quadratic_sample``, compiled).
        """
        return quadratic_sample(self.field, self.origin_xy_m, self.resolution_m, points_xy_m)

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
