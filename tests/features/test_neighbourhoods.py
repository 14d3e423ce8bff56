"""k-NN per level: the true nearest neighbours, in an order set by the points alone."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree

from semantic3d.core.errors import ShapeError
from semantic3d.features.neighbourhoods import LevelIndex, kth_squared_distances


def test_neighbours_are_the_k_nearest_sorted_by_distance() -> None:
    rng = np.random.default_rng(0)
    xyz = rng.uniform(0, 10, (2000, 3))
    keys = rng.permutation(2000).astype(np.int64)
    queries = rng.uniform(0, 10, (300, 3))
    found = LevelIndex(xyz, keys).query(queries, k=10)
    distances, expected = cKDTree(xyz).query(queries, k=10)
    np.testing.assert_array_equal(found.indices, expected)
    np.testing.assert_allclose(found.kth_distance, distances[:, -1], rtol=1e-6)


def test_ties_are_broken_by_key_whatever_the_point_order() -> None:
    grid = np.stack(np.meshgrid(np.arange(6), np.arange(6), np.arange(2), indexing="ij"), -1)
    xyz = grid.reshape(-1, 3).astype(np.float64)  # many equal distances
    keys = np.arange(len(xyz), dtype=np.int64) * 7
    queries = xyz[[0, 14, 40]] + 0.0
    reference = LevelIndex(xyz, keys).query(queries, k=10)
    for seed in range(3):
        order = np.random.default_rng(seed).permutation(len(xyz))
        permuted = LevelIndex(xyz[order], keys[order]).query(queries, k=10)
        np.testing.assert_array_equal(keys[order][permuted.indices], keys[reference.indices])
    # inside a tie the smaller key comes first
    d = np.linalg.norm(xyz[reference.indices] - queries[:, None], axis=2)
    k = keys[reference.indices]
    same = np.isclose(d[:, 1:], d[:, :-1])
    assert np.all(k[:, 1:][same] > k[:, :-1][same])
    assert np.all(np.diff(d, axis=1) >= -1e-6)


@pytest.mark.parametrize("k", [1, 4, 10, 30])
def test_cut_off_ties_resolve_to_the_brute_force_canonical_order(k: int) -> None:
    # an integer lattice (float32 distances exact) with duplicated points: most queries
    # have a tie at the k-th distance that runs past the k + 1 returned neighbours
    rng = np.random.default_rng(k)
    grid = np.stack(np.meshgrid(*(np.arange(9),) * 3, indexing="ij"), -1).reshape(-1, 3)
    xyz = np.vstack([grid, grid[::5]]).astype(np.float64)
    keys = rng.permutation(len(xyz)).astype(np.int64)
    queries = np.vstack([grid[rng.choice(len(grid), 60)], [[20.0, 4, 4], [4, 4, 4.5]]])
    found = LevelIndex(xyz, keys).query(queries, k=k)
    squared = ((xyz[None] - queries[:, None]) ** 2).sum(axis=2)
    expected = np.array([np.lexsort((keys, row))[:k] for row in squared])
    np.testing.assert_array_equal(found.indices, expected)
    kth = np.sqrt(np.take_along_axis(squared, expected[:, -1:], axis=1)[:, 0])
    np.testing.assert_allclose(found.kth_distance, kth)


def test_fewer_points_than_k_returns_all_points() -> None:
    xyz = np.array([[0.0, 0, 0], [1, 0, 0], [0, 2, 0]])
    found = LevelIndex(xyz, np.arange(3, dtype=np.int64)).query(np.zeros((2, 3)), k=10)
    assert found.indices.shape == (2, 3)
    np.testing.assert_array_equal(found.indices[0], [0, 1, 2])
    assert found.kth_distance[0] == pytest.approx(2.0)


def test_empty_index_and_bad_queries_are_rejected() -> None:
    index = LevelIndex(np.empty((0, 3)), np.empty(0, np.int64))
    with pytest.raises(ShapeError, match="empty point set"):
        index.query(np.zeros((1, 3)), k=3)
    with pytest.raises(ShapeError, match=r"queries: expected \(m, 3\)"):
        LevelIndex(np.zeros((2, 3)), np.arange(2, dtype=np.int64)).query(np.zeros((1, 2)), k=1)


@settings(max_examples=60, deadline=None)
@given(
    n=st.integers(1, 300),
    m=st.integers(1, 12),
    k=st.integers(1, 20),
    seed=st.integers(0, 2**32 - 1),
    grid=st.booleans(),
)
def test_the_kth_squared_distance_by_a_scan_is_numpys(
    n: int, m: int, k: int, seed: int, grid: bool
) -> None:
    """The k-th smallest squared distance of each query, ties (points on a grid) and
    repeated points included, is what sorting every distance gives."""
    k = min(k, n)
    rng = np.random.default_rng(seed)
    points = rng.integers(0, 4, (n, 3)).astype(np.float64) if grid else rng.normal(size=(n, 3))
    queries = rng.normal(size=(m, 3))
    expected = np.sort(((queries[:, None, :] - points[None]) ** 2).sum(axis=2), axis=1)[:, k - 1]
    np.testing.assert_allclose(kth_squared_distances(points, queries, k), expected, rtol=1e-12)
