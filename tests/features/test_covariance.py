"""Covariance, moment and height features against a slow float64 reference (np.linalg.eigh)."""

from __future__ import annotations

import numpy as np
import pytest

from semantic3d.core.errors import ShapeError
from semantic3d.features.covariance import (
    DEGENERATE_SUM_M2,
    N_COVARIANCE_COLUMNS,
    as_kernel_indices,
    compute_covariance_features,
    compute_eigen,
    geometry_kernel,
)
from semantic3d.features.height import compute_height_features
from semantic3d.features.names import COVARIANCE_FEATURES, MOMENT_FEATURES

COLUMNS = COVARIANCE_FEATURES + MOMENT_FEATURES
EIGENVECTOR_COLUMNS = {"verticality", "moment1_axis1", "moment1_axis2"}
"""Columns that depend on eigenvector directions (ill-defined for repeated eigenvalues)."""


def reference_features(neighbours: np.ndarray, query: np.ndarray) -> dict[str, float]:
    """Hackel et al. (2016) table 1, one neighbourhood, float64, with np.linalg.eigh."""
    mean = neighbours.mean(axis=0)
    centred = neighbours - mean
    cov = centred.T @ centred / len(neighbours)
    values, vectors = np.linalg.eigh(cov)  # ascending
    l3, l2, l1 = np.maximum(values, 0.0)
    e3, e2, e1 = vectors[:, 0], vectors[:, 1], vectors[:, 2]
    total = l1 + l2 + l3
    if total <= DEGENERATE_SUM_M2:
        return dict.fromkeys(COLUMNS, 0.0)
    eps = np.array([l1, l2, l3]) / total
    offsets = neighbours - query
    return {
        "sum_of_eigenvalues": total,
        "omnivariance": float(np.prod(eps) ** (1 / 3)),
        "eigenentropy": float(-sum(e * np.log(e) for e in eps if e > 0)),
        "anisotropy": (l1 - l3) / l1,
        "planarity": (l2 - l3) / l1,
        "linearity": (l1 - l2) / l1,
        "surface_variation": l3 / total,
        "sphericity": l3 / l1,
        "verticality": 1 - abs(e3[2]),
        "moment1_axis1": abs(float((offsets @ e1).sum())),
        "moment1_axis2": abs(float((offsets @ e2).sum())),
        "moment2_axis1": float(((offsets @ e1) ** 2).sum()),
        "moment2_axis2": float(((offsets @ e2) ** 2).sum()),
    }


def _features_of(points: np.ndarray, neighbours: np.ndarray) -> dict[str, float]:
    row = compute_covariance_features(points, neighbours, points[:1])[0]
    return dict(zip(COLUMNS, row, strict=True))


def _compare(points: np.ndarray, neighbours: np.ndarray, queries: np.ndarray, *, skip=()) -> None:
    got = compute_covariance_features(points, neighbours, queries)
    assert got.dtype == np.float32 and got.shape == (len(queries), len(COLUMNS))
    for row in range(len(queries)):
        expected = reference_features(points[neighbours[row]], queries[row])
        for column, name in enumerate(COLUMNS):
            if name in skip:
                continue
            # omnivariance is a cube root: the ~1e-16 absolute rounding of a zero eigenvalue
            # (any solver, eigh included) becomes ~5e-6 in it.
            tolerance = 1e-5 if name == "omnivariance" else 2e-6
            assert got[row, column] == pytest.approx(expected[name], rel=2e-5, abs=tolerance), (
                f"row {row} {name}"
            )


def test_random_neighbourhoods_match_the_float64_reference() -> None:
    rng = np.random.default_rng(1)
    points = rng.normal(size=(500, 3)) * [3.0, 1.0, 0.3] + [870000.0, 6617000.0, 40.0]
    points -= points[0]  # features run in a frame re-centred on the grid origin
    neighbours = rng.integers(0, 500, (200, 10)).astype(np.int64)
    queries = points[neighbours[:, 0]]
    _compare(points, neighbours, queries)


def test_queries_that_are_not_neighbours_match_the_reference() -> None:
    rng = np.random.default_rng(2)
    points = rng.uniform(-1, 1, (100, 3))
    neighbours = rng.integers(0, 100, (50, 7)).astype(np.int64)
    queries = rng.uniform(-1, 1, (50, 3))
    _compare(points, neighbours, queries)


def test_coplanar_neighbourhood_is_planar_with_a_vertical_normal() -> None:
    rng = np.random.default_rng(3)
    points = np.column_stack([rng.uniform(0, 1, 10), rng.uniform(0, 2, 10), np.full(10, 5.0)])
    neighbours = np.arange(10, dtype=np.int64)[None, :]
    features = _features_of(points, neighbours)
    _compare(points, neighbours, points[:1])
    assert features["sphericity"] == pytest.approx(0.0, abs=1e-6)
    assert features["verticality"] == pytest.approx(0.0, abs=1e-6)  # normal along z
    assert features["planarity"] + features["linearity"] == pytest.approx(1.0, abs=1e-6)


def test_collinear_neighbourhood_is_linear() -> None:
    t = np.linspace(0, 1, 10)
    points = np.column_stack([t, 2 * t, np.zeros(10)])
    neighbours = np.arange(10, dtype=np.int64)[None, :]
    # e2, e3 are any pair orthogonal to the line: only direction-free columns are defined.
    _compare(points, neighbours, points[:1], skip=EIGENVECTOR_COLUMNS - {"moment1_axis1"})
    features = _features_of(points, neighbours)
    assert features["linearity"] == pytest.approx(1.0)
    assert features["moment1_axis2"] == pytest.approx(0.0, abs=1e-6)
    assert 0.0 <= features["verticality"] <= 1.0


def test_duplicate_points_have_no_shape() -> None:
    points = np.tile([[1.0, 2.0, 3.0]], (10, 1))
    neighbours = np.arange(10, dtype=np.int64)[None, :]
    got = compute_covariance_features(points, neighbours, points[:1] + 0.5)
    assert np.array_equal(got, np.zeros_like(got))


def test_two_distinct_points_among_duplicates_match_the_reference() -> None:
    points = np.array([[0.0, 0.0, 0.0]] * 5 + [[0.0, 0.0, 1.0]] * 5)
    neighbours = np.arange(10, dtype=np.int64)[None, :]
    _compare(points, neighbours, points[:1], skip=EIGENVECTOR_COLUMNS - {"moment1_axis1"})
    features = _features_of(points, neighbours)
    assert features["linearity"] == pytest.approx(1.0)
    assert features["sum_of_eigenvalues"] == pytest.approx(0.25)


def test_fewer_neighbours_than_k_match_the_reference() -> None:
    rng = np.random.default_rng(4)
    points = rng.normal(size=(3, 3))
    neighbours = np.array([[0, 1, 2]], dtype=np.int64)
    _compare(points, neighbours, points[:1])


def test_eigen_solver_matches_eigh_on_random_and_repeated_spectra() -> None:
    rng = np.random.default_rng(5)
    a = rng.normal(size=(300, 3, 3))
    matrices = a @ a.transpose(0, 2, 1)  # well separated: closed form
    matrices[:100] = np.eye(3) * rng.uniform(0.1, 2, (100, 1, 1))  # triple: Jacobi
    rotations = np.linalg.qr(rng.normal(size=(100, 3, 3)))[0]
    spectra = np.array([[2.0, 2.0, 0.5], [3.0, 1.0, 1.0], [1.0, 1.0 + 1e-9, 0.0]])[
        np.arange(100) % 3
    ]
    matrices[100:200] = rotations @ (spectra[:, :, None] * rotations.transpose(0, 2, 1))
    values, vectors = compute_eigen(matrices)
    expected = np.linalg.eigvalsh(matrices)[:, ::-1]
    np.testing.assert_allclose(values, expected, rtol=1e-12, atol=1e-12)
    rebuilt = vectors @ (values[:, :, None] * vectors.transpose(0, 2, 1))
    np.testing.assert_allclose(rebuilt, matrices, atol=1e-12)
    np.testing.assert_allclose(
        vectors.transpose(0, 2, 1) @ vectors, np.tile(np.eye(3), (300, 1, 1)), atol=1e-12
    )


def test_height_features_span_the_neighbourhood() -> None:
    points = np.array([[0, 0, 1.0], [0, 0, 3.0], [0, 0, 2.0]])
    got = compute_height_features(points, np.array([[0, 1, 2]], np.int64), np.array([[0, 0, 2.5]]))
    np.testing.assert_allclose(got, [[2.0, 1.5, 0.5]])


@pytest.mark.parametrize("dtype", [np.int64, np.int32, np.uint32])
def test_the_fused_kernel_is_the_covariance_and_height_kernels_bit_for_bit(dtype: type) -> None:
    rng = np.random.default_rng(7)
    points = rng.normal(size=(500, 3)) * [5.0, 5.0, 0.5]
    points[:40] = points[0]  # duplicate points: shapeless neighbourhoods
    neighbours = np.sort(rng.integers(0, 500, size=(400, 10)), axis=1).astype(dtype)
    neighbours[:20] = np.arange(10)
    queries = points[rng.integers(0, 500, size=400)] + rng.normal(size=(400, 3)) * 0.1
    fused = np.empty((400, N_COVARIANCE_COLUMNS + 3), np.float32)
    geometry_kernel(points, as_kernel_indices(neighbours, 500), queries, fused, True, 3)
    separate = np.hstack(
        [
            compute_covariance_features(points, neighbours, queries),
            compute_height_features(points, neighbours, queries),
        ]
    )
    assert np.array_equal(fused.view(np.uint32), separate.view(np.uint32))


def test_every_index_type_reaches_the_kernels_as_uint32() -> None:
    neighbours = np.array([[0, 2], [1, 1]], np.int64)
    indices = as_kernel_indices(neighbours[:, ::-1], 3)  # a strided view too
    assert indices.dtype == np.uint32 and indices.flags.c_contiguous
    assert indices.tolist() == [[2, 0], [1, 1]]
    with pytest.raises(ShapeError, match=r"indices in 0\.\.2"):
        as_kernel_indices(np.array([[-1, 0]]), 3)


@pytest.mark.parametrize(
    ("neighbours", "queries", "match"),
    [
        (np.zeros((2, 3), np.float64), np.zeros((2, 3)), "neighbours: expected"),
        (np.zeros((2,), np.int64), np.zeros((2, 3)), "neighbours: expected"),
        (np.zeros((2, 3), np.int64), np.zeros((3, 3)), "queries: expected"),
        (np.full((2, 3), 7, np.int64), np.zeros((2, 3)), "indices in 0..4"),
    ],
)
def test_bad_inputs_are_rejected(neighbours: np.ndarray, queries: np.ndarray, match: str) -> None:
    with pytest.raises(ShapeError, match=match):
        compute_covariance_features(np.zeros((5, 3)), neighbours, queries)
