"""Euclidean distance transform and connected-component labelling of grids, without importing scipy, and the
quadratic sampling of a smooth field that scan matching evaluates thousands of times per scan.

``distance_transform_edt`` and ``label`` compute what ``scipy.ndimage``'s functions of the same names compute for
the cases the services use (2-D distance with one isotropic cell size; 2-D or 3-D labels with every neighbour of the
3^n - 1 neighbourhood connected), through the small C extension ``services/common/_gridops.c`` built at install.
Importing ``scipy.ndimage`` loads ``scipy.special`` and ``numpy.testing``, about 30 MB resident in each process that
does it; nav and localization need only these two operations. Where no C compiler was available at install, both
fall back to ``scipy.ndimage`` (imported then, on first use). ``quadratic_sample`` falls back to the same arithmetic in
NumPy, which is about 30x slower on a scan's few hundred points (its cost is NumPy's per-call overhead).
"""

from __future__ import annotations

import numpy as np

try:
    import services.common._gridops as _gridops
except ImportError:  # built at install where a C compiler was available (setup.py)
    _gridops = None
# an extension built from an older source lacks the newer entry points: each falls back to NumPy on its own
_compiled_quadratic_sample = getattr(_gridops, "quadratic_sample", None)
_compiled_max_gaussian_splat = getattr(_gridops, "max_gaussian_splat", None)


def distance_transform_edt(grid: np.ndarray, sampling: float = 1.0) -> np.ndarray:
    """Distance (cells x ``sampling``) from each nonzero cell of a 2-D grid to the centre of the nearest zero cell
    (0 on zero cells): d = sampling * sqrt(di^2 + dj^2), exact. A grid without zero cells is inf everywhere."""
    grid = np.asarray(grid)
    if grid.ndim != 2:
        raise ValueError(f"distance_transform_edt: expected a 2-D grid, got {grid.ndim} dimensions")
    if _gridops is None or not grid.size:
        from scipy import ndimage

        if grid.size and grid.all():
            return np.full(grid.shape, np.inf)
        return np.asarray(ndimage.distance_transform_edt(grid, sampling=sampling), dtype=float)
    d2 = np.frombuffer(_gridops.edt_sq(np.ascontiguousarray(grid != 0, dtype=np.uint8)), dtype=np.float64)
    d = np.sqrt(d2).reshape(grid.shape)
    if sampling != 1.0:
        d *= sampling
    return d


def label(grid: np.ndarray) -> tuple[np.ndarray, int]:
    """(int32 labels, count) of the connected components of the nonzero cells of a 2-D or 3-D grid, diagonal
    neighbours connected (``scipy.ndimage.label(grid, structure=np.ones((3,) * grid.ndim))``): components are
    numbered 1..count in the C order of their first cell, 0 is the background."""
    grid = np.asarray(grid)
    if grid.ndim not in (2, 3):
        raise ValueError(f"label: expected a 2-D or 3-D grid, got {grid.ndim} dimensions")
    if _gridops is None or not grid.size:
        from scipy import ndimage

        labels, count = ndimage.label(grid, structure=np.ones((3,) * grid.ndim, dtype=bool))
        return np.asarray(labels, dtype=np.int32), int(count)
    raw, count = _gridops.label(np.ascontiguousarray(grid != 0, dtype=np.uint8))
    return np.frombuffer(raw, dtype=np.int32).reshape(grid.shape), int(count)


def quadratic_sample(field: np.ndarray, origin_xy_m: np.ndarray, resolution_m: float, points_xy_m: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
    """M(p) and ∇M(p) (per metre) of a float32 field (``field[iy, ix]``, cell centres at origin + (i + 0.5) * res)
    at points (N, 2); 0 where the 3x3 neighbourhood of the nearest centre leaves the field.

    Second-order Taylor expansion about the nearest cell centre c: M(c + δ) ≈ M_c + gᵀδ + ½ δᵀHδ with g, H from
    central differences of the 3x3 neighbourhood (δ in cells). The C path and the NumPy path give the same bits.
    """
    field = np.ascontiguousarray(field, dtype=np.float32)
    points = np.ascontiguousarray(points_xy_m, dtype=np.float64).reshape(-1, 2)
    if _compiled_quadratic_sample is not None:
        n = len(points)
        out = np.frombuffer(_compiled_quadratic_sample(field, float(origin_xy_m[0]), float(origin_xy_m[1]),
                                                      float(resolution_m), points), dtype=np.float64)
        return out[:n], out[n:].reshape(n, 2)
    return _quadratic_sample_numpy(field, origin_xy_m, resolution_m, points)


def _quadratic_sample_numpy(field: np.ndarray, origin_xy_m: np.ndarray, resolution_m: float, points: np.ndarray
                            ) -> tuple[np.ndarray, np.ndarray]:
    """``quadratic_sample`` in NumPy (the fallback without the C extension, and its reference in tests)."""
    height, width = field.shape
    u = (points[:, 0] - origin_xy_m[0]) / resolution_m - 0.5
    v = (points[:, 1] - origin_xy_m[1]) / resolution_m - 0.5
    x = np.rint(u).astype(np.intp)
    y = np.rint(v).astype(np.intp)
    ok = (x >= 1) & (y >= 1) & (x < width - 1) & (y < height - 1)
    x[~ok] = 1
    y[~ok] = 1
    du = u - x
    dv = v - y
    flat = field.ravel()
    i = y * width + x
    c = flat.take(i)
    e, w = flat.take(i + 1), flat.take(i - 1)
    n, s = flat.take(i + width), flat.take(i - width)
    gx = 0.5 * (e - w)
    gy = 0.5 * (n - s)
    hxx = e - 2.0 * c + w
    hyy = n - 2.0 * c + s
    hxy = 0.25 * (flat.take(i + width + 1) - flat.take(i - width + 1) - flat.take(i + width - 1)
                  + flat.take(i - width - 1))
    value = c + gx * du + gy * dv + 0.5 * (hxx * du * du + 2.0 * hxy * du * dv + hyy * dv * dv)
    grad = np.stack([gx + hxx * du + hxy * dv, gy + hxy * du + hyy * dv], axis=1) / resolution_m
    value = np.where(ok, value, 0.0)
    grad[~ok] = 0.0
    return value, grad


def max_gaussian_splat(field: np.ndarray, origin_xy_m: np.ndarray, resolution_m: float, sigma_cells: float,
                       points_xy_m: np.ndarray) -> None:
    """In place: field[iy, ix] = max(field[iy, ix], exp(−d² / 2σ²)) over the points (N, 2), d the distance in cells
    from the cell centre (origin + (i + 0.5) * res) to the point, for every centre within ⌈3σ⌉ cells (a square
    window) of the point's nearest centre; ``field`` is a C-contiguous float32 array, and cells beyond it are
    skipped. The field is then the likelihood field M(p) = exp(−d(p)² / 2σ²) of the distance d(p) to the nearest
    point (Thrun et al., Probabilistic Robotics §6.4), truncated at 3σ, sampled at cell centres."""
    if field.dtype != np.float32 or not field.flags.c_contiguous or field.ndim != 2:
        raise ValueError("max_gaussian_splat: expected a C-contiguous 2-D float32 field")
    if not resolution_m > 0.0 or not sigma_cells > 0.0:
        raise ValueError("max_gaussian_splat: resolution and sigma must be > 0")
    points = np.ascontiguousarray(points_xy_m, dtype=np.float64).reshape(-1, 2)
    radius = int(np.ceil(3.0 * sigma_cells))
    if _compiled_max_gaussian_splat is not None:
        _compiled_max_gaussian_splat(field, float(origin_xy_m[0]), float(origin_xy_m[1]), float(resolution_m),
                                     float(sigma_cells), radius, points)
        return
    _max_gaussian_splat_numpy(field, origin_xy_m, resolution_m, sigma_cells, radius, points)


def _max_gaussian_splat_numpy(field: np.ndarray, origin_xy_m: np.ndarray, resolution_m: float, sigma_cells: float,
                              radius: int, points: np.ndarray) -> None:
    """``max_gaussian_splat`` in NumPy (the fallback without the C extension, and its reference in tests)."""
    height, width = field.shape
    points = points[np.isfinite(points).all(axis=1)]
    u = (points[:, 0] - origin_xy_m[0]) / resolution_m - 0.5
    v = (points[:, 1] - origin_xy_m[1]) / resolution_m - 0.5
    offsets = np.arange(-radius, radius + 1)
    x = np.rint(u).astype(np.intp)[:, None] + offsets[None, :]
    centre_y = np.rint(v).astype(np.intp)
    for dy in offsets:  # one window row at a time: (N, 2r + 1) temporaries instead of (N, (2r + 1)²)
        y = centre_y + dy
        d2 = (x - u[:, None]) ** 2 + ((y - v) ** 2)[:, None]
        value = np.exp(-d2 / (2.0 * sigma_cells**2)).astype(np.float32)
        inside = (x >= 0) & (x < width) & ((y >= 0) & (y < height))[:, None]
        np.maximum.at(field.ravel(), (np.broadcast_to(y[:, None], x.shape) * width + x)[inside], value[inside])
