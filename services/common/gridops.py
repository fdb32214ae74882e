"""Euclidean distance transform and connected-component labelling of grids, without importing scipy.

``distance_transform_edt`` and ``label`` compute what ``scipy.ndimage``'s functions of the same names compute for
the cases the services use (2-D distance with one isotropic cell size; 2-D or 3-D labels with every neighbour of the
3^n - 1 neighbourhood connected), through the small C extension ``services/common/_gridops.c`` built at install.
Importing ``scipy.ndimage`` loads ``scipy.special`` and ``numpy.testing``, about 30 MB resident in each process that
does it; nav and localization need only these two operations. Where no C compiler was available at install, both
fall back to ``scipy.ndimage`` (imported then, on first use).
"""

from __future__ import annotations

import numpy as np

try:
    import services.common._gridops as _gridops
except ImportError:  # built at install where a C compiler was available (setup.py)
    _gridops = None


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
