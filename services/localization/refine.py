"""Scan-to-map refinement at rest: the most probable pose of one dense scan near the filter's estimate (core).

The particle filter weighs a subsampled scan (``max_beams``, 60 by default) looked up at the nearest cell corner,
and reports the mean of a cloud a few centimetres wide; along a corridor the few beams that see its ends pin the
pose only loosely, and that mean can sit several centimetres off. When the robot stands still and a precise pose
matters (nav's goal checker asks for an update without motion before it judges a goal) every valid beam of the
scan is scored against the map's distance field, interpolated bilinearly between cell corners (no quantisation to
the cell size, which matters on a 0.25 m map), and the pose maximising

    J(q) = sum over beams b of log(z_hit exp(-d_b(q)^2 / (2 sigma_hit^2)) + z_rand / range_max)
           - 1/2 (q - q0)^T S^-1 (q - q0)

is searched around the estimate q0: the scan likelihood times the filter's own belief as a Gaussian prior (its
covariance S, at least ``prior_min_m`` / ``prior_min_rad``), so that along a direction the scan does not constrain
(a long corridor, an open hall with one wall in view) the estimate stays where the filter put it instead of
following the ripples of the field. The search is a grid of ``steps`` per axis over a window of 3 sigma of S
(clipped to ``min_window`` .. ``max_window``), then the same grid over half that span around the best, ``levels``
times. Beams that reach their endpoint through an occupied cell score as misses (``log_likelihood``). The result
is used only when it lies strictly inside the window (a maximum on the edge means the scan fits
somewhere the filter does not believe in: its estimate stays).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from services.common.se2 import wrap_angle

try:
    import services.localization._refine as _refine
except ImportError:  # built at install where a C compiler was available (setup.py); NumPy below otherwise
    _refine = None

Pose = tuple[float, float, float]


@dataclass(frozen=True)
class BeamModel:
    """The likelihood-field beam model: ``pz(d) = z_hit exp(-d^2 / (2 sigma_hit^2)) + rand_density``; endpoints
    beyond the map score at ``max_dist_m``."""

    z_hit: float
    rand_density: float
    sigma_hit: float
    max_dist_m: float

    def log_pz(self, d: np.ndarray) -> np.ndarray:
        log_p: np.ndarray = np.log(np.maximum(self.z_hit * np.exp(-np.square(d) / (2.0 * self.sigma_hit ** 2))
                                              + self.rand_density, 1e-300))
        return log_p


@dataclass(frozen=True)
class RefineParams:
    """Search window and prior floor (m, rad); see the module docstring."""

    #: at least a wall's thickness, so that a filter that slid by one (see log_likelihood) finds its way back
    min_window_m: float = 0.12
    max_window_m: float = 0.15
    min_window_rad: float = 0.015
    max_window_rad: float = 0.05
    prior_min_m: float = 0.03
    prior_min_rad: float = 0.01
    steps: int = 7
    levels: int = 5
    #: beams scored at most; the rest are thinned evenly
    max_beams: int = 541


@dataclass
class Refinement:
    pose: Pose
    gain: float  # J(refined) - J(start)
    used: bool
    beams: int


def interpolated_distance(distance_m: np.ndarray, origin: tuple[float, float, float], resolution: float,
                          x: np.ndarray, y: np.ndarray, outside_m: float) -> np.ndarray:
    """Bilinear interpolation of a per-corner field (corner (i, j) at origin + R(yaw) (j, i) * resolution) at map
    points. Beyond the corners: the field at the nearest edge point plus the distance to it, at most ``outside_m``
    (the map's edge can be a surface: a beam that ends a centimetre past it, by range noise, is a hit there, not a
    beam ending nowhere; scoring it as the latter pulled poses 3 cm inwards on a map whose free space reaches its
    edge). ``outside_m`` NaN: NaN beyond the corners."""
    ox, oy, oyaw = origin
    c0, s0 = math.cos(oyaw), math.sin(oyaw)
    dx, dy = x - ox, y - oy
    u = (c0 * dx + s0 * dy) / resolution
    v = (-s0 * dx + c0 * dy) / resolution
    h, w = distance_m.shape
    uc = np.clip(u, 0, w - 1.000001)
    vc = np.clip(v, 0, h - 1.000001)
    beyond_m = np.hypot(u - uc, v - vc) * resolution
    j, i = uc.astype(np.intp), vc.astype(np.intp)
    fu, fv = uc - j, vc - i
    d = ((distance_m[i, j] * (1 - fu) + distance_m[i, j + 1] * fu) * (1 - fv)
         + (distance_m[i + 1, j] * (1 - fu) + distance_m[i + 1, j + 1] * fu) * fv)
    result: np.ndarray = np.where(beyond_m > 0.0, np.minimum(d + beyond_m, np.maximum(d, outside_m)), d)
    return result


def cells_set(mask: np.ndarray, origin: tuple[float, float, float], resolution: float, x: np.ndarray, y: np.ndarray
              ) -> np.ndarray:
    """Whether the cells of ``mask`` (row 0 at the origin) holding map points are set (False beyond the map)."""
    ox, oy, oyaw = origin
    c0, s0 = math.cos(oyaw), math.sin(oyaw)
    dx, dy = x - ox, y - oy
    j = np.floor((c0 * dx + s0 * dy) / resolution).astype(np.intp)
    i = np.floor((-s0 * dx + c0 * dy) / resolution).astype(np.intp)
    h, w = mask.shape
    inside = (i >= 0) & (i < h) & (j >= 0) & (j < w)
    out = np.zeros(x.shape, dtype=bool)
    out[inside] = mask[i[inside], j[inside]]
    return out


def beam_rays(poses: np.ndarray, bearings: np.ndarray, mount: Pose) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The laser's map-frame origin (k,) x and y seen from each of ``poses`` (k, 3) (pose ∘ mount) and the map-frame
    angle (k, n) of each of n beams."""
    mx, my, mth = mount
    th = poses[:, 2]
    lx = poses[:, 0] + np.cos(th) * mx - np.sin(th) * my
    ly = poses[:, 1] + np.sin(th) * mx + np.cos(th) * my
    return lx, ly, (th + mth)[:, None] + bearings[None, :]


def log_likelihood(distance_m: np.ndarray, origin: tuple[float, float, float], resolution: float, model: BeamModel,
                   poses: np.ndarray, ranges: np.ndarray, bearings: np.ndarray, mount: Pose,
                   occupied: np.ndarray | None = None, clearance_m: float = 0.05) -> np.ndarray:
    """Sum over beams of log pz at the endpoints of the beams seen from each of ``poses`` (k, 3).

    With ``occupied`` (cells, the map's raster): a beam whose last stretch before its endpoint, from
    ``clearance_m`` to ``clearance_m`` + 1.5 cells short of it, crosses an occupied cell went through a wall to get
    there and scores as a beam ending ``max_dist_m`` from any (the distance field alone, measured from both faces
    of a wall, scores a pose shifted by a wall's thickness as well as the true one).

    Runs in the C extension ``_refine.c`` (same arithmetic, about 1e-12 relative apart; a 541-beam refinement
    takes about 50 ms instead of 270) where it was built, else in NumPy (``log_likelihood_numpy``, also the
    reference in tests)."""
    distance_m = np.asarray(distance_m)
    if _refine is None or distance_m.ndim != 2 or min(distance_m.shape) < 2:
        return log_likelihood_numpy(distance_m, origin, resolution, model, poses, ranges, bearings, mount, occupied,
                                    clearance_m)
    occ = None if occupied is None else np.ascontiguousarray(occupied, dtype=bool).view(np.uint8)
    poses = np.ascontiguousarray(poses, dtype=np.float64).reshape(-1, 3)
    raw = _refine.log_likelihood(
        np.ascontiguousarray(distance_m, dtype=np.float64), occ, float(origin[0]), float(origin[1]),
        float(origin[2]), float(resolution), float(model.z_hit), float(model.rand_density),
        2.0 * float(model.sigma_hit) ** 2, float(model.max_dist_m), poses,
        np.ascontiguousarray(ranges, dtype=np.float64), np.ascontiguousarray(bearings, dtype=np.float64),
        float(mount[0]), float(mount[1]), float(mount[2]), float(clearance_m))
    return np.frombuffer(raw, dtype=np.float64)


def log_likelihood_numpy(distance_m: np.ndarray, origin: tuple[float, float, float], resolution: float,
                         model: BeamModel, poses: np.ndarray, ranges: np.ndarray, bearings: np.ndarray, mount: Pose,
                         occupied: np.ndarray | None = None, clearance_m: float = 0.05) -> np.ndarray:
    """``log_likelihood`` in NumPy."""
    lx, ly, ga = beam_rays(poses, bearings, mount)
    ex = lx[:, None] + ranges[None, :] * np.cos(ga)
    ey = ly[:, None] + ranges[None, :] * np.sin(ga)
    d = interpolated_distance(distance_m, origin, resolution, ex, ey, model.max_dist_m)
    if occupied is not None:
        through = np.zeros(d.shape, dtype=bool)
        for back_m in clearance_m + resolution * np.array([0.0, 0.5, 1.0, 1.5]):
            short = np.maximum(ranges - back_m, 0.0)[None, :]
            through |= cells_set(occupied, origin, resolution, lx[:, None] + short * np.cos(ga),
                                 ly[:, None] + short * np.sin(ga))
        d = np.where(through, model.max_dist_m, d)
    total: np.ndarray = model.log_pz(d).sum(axis=1)
    return total


def refine_pose(distance_m: np.ndarray, origin: tuple[float, float, float], resolution: float, model: BeamModel,
                start: Pose, covariance: np.ndarray, ranges: np.ndarray, bearings: np.ndarray, mount: Pose,
                params: RefineParams | None = None, occupied: np.ndarray | None = None) -> Refinement:
    """The most probable pose near ``start`` for one scan and the filter's covariance (module docstring)."""
    p = params or RefineParams()
    ranges = np.asarray(ranges, dtype=np.float64)
    bearings = np.asarray(bearings, dtype=np.float64)
    if ranges.size > p.max_beams:
        keep = np.linspace(0, ranges.size - 1, p.max_beams).round().astype(np.intp)
        ranges, bearings = ranges[keep], bearings[keep]
    if ranges.size == 0:
        return Refinement(start, 0.0, False, 0)
    cov = np.asarray(covariance, dtype=np.float64).reshape(3, 3)
    prior = np.diag([p.prior_min_m ** 2, p.prior_min_m ** 2, p.prior_min_rad ** 2])
    prior_cov = np.maximum(cov, 0.0) * np.eye(3) + prior if not np.all(np.isfinite(cov)) else cov + prior
    info = np.linalg.inv(prior_cov)
    sxy = math.sqrt(max(float(prior_cov[0, 0]), float(prior_cov[1, 1])))
    sth = math.sqrt(float(prior_cov[2, 2]))
    win = np.array([min(max(3.0 * sxy, p.min_window_m), p.max_window_m),
                    min(max(3.0 * sxy, p.min_window_m), p.max_window_m),
                    min(max(3.0 * sth, p.min_window_rad), p.max_window_rad)])
    base = np.asarray(start, dtype=np.float64)

    def objective(cand: np.ndarray) -> np.ndarray:
        dq = cand - base
        score: np.ndarray = (log_likelihood(distance_m, origin, resolution, model, cand, ranges, bearings, mount,
                                            occupied)
                             - 0.5 * np.einsum("ki,ij,kj->k", dq, info, dq))
        return score

    start_j = float(objective(base[None, :])[0])
    best, best_j = base.copy(), start_j
    span = win.copy()
    offsets = np.linspace(-1.0, 1.0, p.steps)
    ox, oy, ot = np.meshgrid(offsets, offsets, offsets, indexing="ij")
    unit = np.column_stack([ox.ravel(), oy.ravel(), ot.ravel()])
    for _ in range(p.levels):
        cand = best[None, :] + unit * span
        j = objective(cand)
        k = int(np.argmax(j))
        if j[k] > best_j:
            best, best_j = cand[k].copy(), float(j[k])
        span = span / 2.0
    used = bool(np.all(np.abs(best - base) < win * 0.999))
    pose = (float(best[0]), float(best[1]), wrap_angle(float(best[2])))
    return Refinement(pose if used else start, best_j - start_j, used, int(ranges.size))
