"""services.common.gridops against scipy.ndimage, the reference it replaces in nav and localization."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from scipy import ndimage

from services.common import gridops


@pytest.mark.parametrize("seed", range(40))
def test_distance_transform_matches_scipy(seed: int) -> None:
    rng = np.random.default_rng(seed)
    h, w = (int(v) for v in rng.integers(1, 70, 2))
    grid = rng.random((h, w)) < rng.uniform(0.3, 0.999)
    grid.flat[int(rng.integers(grid.size))] = False  # at least one zero cell
    exact = gridops.distance_transform_edt(grid)
    assert np.array_equal(exact, ndimage.distance_transform_edt(grid))  # sqrt of an exact integer: bit for bit
    for sampling in (0.05, 0.03):
        d = gridops.distance_transform_edt(grid, sampling=sampling)
        np.testing.assert_allclose(d, ndimage.distance_transform_edt(grid, sampling=sampling), rtol=1e-12, atol=0)


def test_distance_transform_edge_cases() -> None:
    assert np.all(np.isinf(gridops.distance_transform_edt(np.ones((3, 4), bool))))  # no zero cell
    assert np.array_equal(gridops.distance_transform_edt(np.zeros((2, 2), bool)), np.zeros((2, 2)))
    line = np.ones((1, 6), bool)
    line[0, 0] = False
    assert gridops.distance_transform_edt(line, sampling=0.5).tolist() == [[0.0, 0.5, 1.0, 1.5, 2.0, 2.5]]
    with pytest.raises(ValueError, match="2-D"):
        gridops.distance_transform_edt(np.ones(5, bool))


@pytest.mark.parametrize("seed", range(40))
def test_label_matches_scipy_in_2d_and_3d(seed: int) -> None:
    rng = np.random.default_rng(100 + seed)
    h, w = (int(v) for v in rng.integers(1, 50, 2))
    for shape in ((h, w), (int(rng.integers(1, 9)), h, w)):
        grid = rng.random(shape) < rng.uniform(0.05, 0.7)
        labels, count = gridops.label(grid)
        ref, ref_count = ndimage.label(grid, structure=np.ones((3,) * len(shape), dtype=bool))
        assert count == ref_count
        assert np.array_equal(labels, ref)  # same numbering: components in the C order of their first cell
        assert labels.dtype == np.int32


def test_label_diagonals_connect_and_bad_shapes_are_refused() -> None:
    grid = np.eye(4, dtype=bool)
    grid[0, 3] = True
    labels, count = gridops.label(grid)
    assert count == 2 and labels[3, 3] == 1 and labels[0, 3] == 2
    with pytest.raises(ValueError, match="2-D or 3-D"):
        gridops.label(np.ones((2, 2, 2, 2), bool))


def test_compiled_and_no_scipy_in_nav_and_localization() -> None:
    """The extension is built (make install), and nav's and localization's nodes run without importing scipy."""
    assert gridops._gridops is not None, "services/common/_gridops.c was not built (pip install -e .)"
    code = ("import sys, services.nav.__main__, services.localization.__main__; "
            "print(sorted(m for m in sys.modules if m.split('.')[0] == 'scipy'))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_quadratic_sample_compiled_gives_numpy_bits(seed: int) -> None:
    """The compiled sampling gives exactly the NumPy arithmetic's values and gradients, inside the field, on its
    border cells (zero) and beyond it, on half-cell ties (rint rounds half to even) and at NaN points (zero)."""
    rng = np.random.default_rng(seed)
    field = rng.random((37, 53)).astype(np.float32)
    origin, res = np.array([-1.3, 2.1]), 0.05
    points = np.column_stack([rng.uniform(-1.6, 1.6, 4000), rng.uniform(1.8, 4.2, 4000)])
    ties = origin + (np.array([[7.0, 9.0], [8.0, 3.0], [1.0, 1.0], [51.0, 35.0]]) + 0.5 + 0.5) * res
    points = np.vstack([points, ties, [[np.nan, 2.5], [0.0, np.inf]]])
    value, grad = gridops.quadratic_sample(field, origin, res, points)
    ref_value, ref_grad = gridops._quadratic_sample_numpy(field, origin, res, points)
    assert gridops._compiled_quadratic_sample is not None, "the C extension was not built (make install)"
    assert np.array_equal(value, ref_value) and np.array_equal(grad, ref_grad)
    inside = (value != 0.0).sum()
    assert 0 < inside < len(points)  # both branches were exercised
    assert np.all(value[-2:] == 0.0) and np.all(grad[-2:] == 0.0)


def test_quadratic_sample_refuses_wrong_types() -> None:
    if gridops._gridops is None:
        pytest.skip("needs the C extension (make install with a C compiler)")
    with pytest.raises(ValueError, match="float32 field"):
        gridops._gridops.quadratic_sample(np.zeros((4, 4)), 0.0, 0.0, 0.1, np.zeros((1, 2)))
    with pytest.raises(ValueError, match=r"shape \(N, 2\)"):
        gridops._gridops.quadratic_sample(np.zeros((4, 4), np.float32), 0.0, 0.0, 0.1, np.zeros((2, 3)))


def test_an_extension_built_from_older_source_falls_back_to_numpy(monkeypatch) -> None:
    """An extension built before ``quadratic_sample`` existed lacks it: sampling falls back, it does not raise."""
    monkeypatch.setattr(gridops, "_compiled_quadratic_sample", None)
    field = np.arange(36, dtype=np.float32).reshape(6, 6)
    value, grad = gridops.quadratic_sample(field, np.zeros(2), 0.1, np.array([[0.25, 0.25]]))
    ref_value, ref_grad = gridops._quadratic_sample_numpy(field, np.zeros(2), 0.1, np.array([[0.25, 0.25]]))
    assert value[0] != 0.0 and np.array_equal(value, ref_value) and np.array_equal(grad, ref_grad)


def _nearest_point_field(shape: tuple[int, int], origin: np.ndarray, res: float, sigma_cells: float,
                         points: np.ndarray) -> np.ndarray:
    """exp(−d²/2σ²) of each cell centre's distance d (cells) to the nearest point whose nearest centre is within
    ⌈3σ⌉ cells in x and y: the definition ``max_gaussian_splat`` implements, by brute force."""
    radius = int(np.ceil(3.0 * sigma_cells))
    iy, ix = np.mgrid[0:shape[0], 0:shape[1]]
    u = (points[:, 0] - origin[0]) / res - 0.5
    v = (points[:, 1] - origin[1]) / res - 0.5
    field = np.zeros(shape, np.float32)
    for pu, pv in zip(u, v, strict=True):
        near = (np.abs(ix - np.rint(pu)) <= radius) & (np.abs(iy - np.rint(pv)) <= radius)
        value = np.exp(-((ix - pu) ** 2 + (iy - pv) ** 2) / (2.0 * sigma_cells**2)).astype(np.float32)
        field = np.where(near, np.maximum(field, value), field)
    return field


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_max_gaussian_splat_is_the_nearest_point_field_in_c_and_numpy(seed: int) -> None:
    """The compiled splat gives the NumPy fallback's bits, and both the brute-force nearest-point field, for points
    inside the field, near and beyond its border (windows clipped), and NaN/inf points (skipped)."""
    rng = np.random.default_rng(seed)
    shape, origin, res, sigma = (31, 43), np.array([-0.7, 1.3]), 0.05, 1.5
    points = np.column_stack([rng.uniform(-1.0, 1.6, 300), rng.uniform(1.0, 3.2, 300)])
    points = np.vstack([points, [[np.nan, 2.0], [0.3, np.inf]]])
    compiled = np.zeros(shape, np.float32)
    gridops.max_gaussian_splat(compiled, origin, res, sigma, points)
    fallback = np.zeros(shape, np.float32)
    gridops._max_gaussian_splat_numpy(fallback, origin, res, sigma, int(np.ceil(3 * sigma)), points)
    assert gridops._compiled_max_gaussian_splat is not None, "the C extension was not built (make install)"
    assert np.array_equal(compiled, fallback)
    expected = _nearest_point_field(shape, origin, res, sigma, points[:-2])
    assert np.allclose(compiled, expected, atol=1e-7)
    beyond = (points[:-2, 0] < origin[0]) | (points[:-2, 1] < origin[1]) | (points[:-2, 1] > origin[1] + shape[0] * res)
    assert beyond.any() and compiled.min() >= 0.0 and compiled.max() > 0.9  # windows were clipped at the border
    assert compiled.max() <= 1.0


def test_max_gaussian_splat_peaks_at_one_on_every_point_however_sparse() -> None:
    """Unlike a blur of splatted hits (a sum), the field along a row of points is 1 at each point whatever their
    spacing: no slope from dense to sparse for a scan to slide down."""
    res = 0.05
    xs = np.round(np.concatenate([np.arange(0.0, 1.0, 0.05), np.arange(1.0, 3.0, 0.5)]), 6)  # then 10x sparser
    points = np.column_stack([xs, np.full(len(xs), 0.5)]) + 0.5 * res  # on cell centres
    field = np.zeros((20, 70), np.float32)
    gridops.max_gaussian_splat(field, np.array([-0.2, 0.0]), res, 1.5, points)
    row = field[10]
    on_points = np.rint((xs + 0.2) / res).astype(int)
    assert np.allclose(row[on_points], 1.0)
    assert row[on_points[-2] + 5] < 0.01  # half-way between sparse points: the field dips to the floor


def test_max_gaussian_splat_refuses_wrong_types() -> None:
    with pytest.raises(ValueError, match="float32 field"):
        gridops.max_gaussian_splat(np.zeros((4, 4)), np.zeros(2), 0.1, 1.5, np.zeros((1, 2)))
    with pytest.raises(ValueError, match="must be > 0"):
        gridops.max_gaussian_splat(np.zeros((4, 4), np.float32), np.zeros(2), 0.0, 1.5, np.zeros((1, 2)))
    if gridops._gridops is None:
        return
    with pytest.raises(ValueError, match=r"shape \(N, 2\)"):
        gridops._gridops.max_gaussian_splat(np.zeros((4, 4), np.float32), 0.0, 0.0, 0.1, 1.5, 5, np.zeros((2, 3)))
    with pytest.raises(ValueError, match="writable"):
        gridops._gridops.max_gaussian_splat(np.zeros((4, 4)), 0.0, 0.0, 0.1, 1.5, 5, np.zeros((1, 2)))
