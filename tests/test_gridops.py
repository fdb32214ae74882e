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
