"""The k-d tree against a brute-force reference: the k smallest (float32 distance, index)
pairs, with nanoflann's distance arithmetic, whatever the thread count."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from semantic3d.core.errors import ShapeError
from semantic3d.core.threads import thread_limit
from semantic3d.spatial import kdtree
from semantic3d.spatial.kdtree import KdTree


def _brute_force(points: np.ndarray, queries: np.ndarray, k: int) -> tuple[np.ndarray, ...]:
    difference = queries[:, None, :] - points[None, :, :]
    squared = difference * difference
    distance = (squared[..., 0] + squared[..., 1]) + squared[..., 2]  # float32, in that order
    index = np.broadcast_to(np.arange(points.shape[0]), distance.shape)
    order = np.lexsort((index, distance), axis=1)[:, :k]
    return order, np.take_along_axis(distance, order, axis=1)


@settings(max_examples=40, deadline=None)
@given(
    n=st.integers(1, 300),
    m=st.integers(1, 60),
    k=st.integers(1, 25),
    grid=st.sampled_from([0.0, 0.25, 1.0]),
    seed=st.integers(0, 2**16),
)
def test_the_k_nearest_are_those_of_a_brute_force_search(
    n: int, m: int, k: int, grid: float, seed: int
) -> None:
    rng = np.random.default_rng(seed)
    points = (rng.random((n, 3)) * 4).astype(np.float32)
    if grid:  # snapped to a grid: many equal distances, duplicated points
        points = (np.round(points / grid) * grid).astype(np.float32)
    queries = np.concatenate([points[: m // 2], (rng.random((m - m // 2, 3)) * 4)]).astype(
        np.float32
    )
    k = min(k, n)
    indices, squared = KdTree(points, leaf_size=4).query(queries, k=k)
    expected_indices, expected_squared = _brute_force(points, queries, k)
    assert np.array_equal(indices, expected_indices)
    assert np.array_equal(squared, expected_squared)


@settings(max_examples=40, deadline=None)
@given(
    n=st.integers(1, 400),
    k=st.integers(1, 20),
    grid=st.sampled_from([0.0, 0.5, 4.0]),
    seed=st.integers(0, 2**16),
)
def test_top_levels_split_on_every_thread_give_the_brute_force_results(
    n: int, k: int, grid: float, seed: int
) -> None:
    """Nodes split about a sampled pivot on several threads (every node of the top levels
    here), and at the median where the pivot splits them badly (grid = 4: duplicates)."""
    rng = np.random.default_rng(seed)
    points = (rng.random((n, 3)) * 4).astype(np.float32)
    if grid:
        points = (np.round(points / grid) * grid).astype(np.float32)
    queries = np.concatenate([points[:20], rng.random((20, 3)) * 4]).astype(np.float32)
    k = min(k, n)
    saved = kdtree._PARALLEL_SPLIT_ROWS
    kdtree._PARALLEL_SPLIT_ROWS = 2
    try:
        with thread_limit(8):
            tree = KdTree(points, leaf_size=2)
    finally:
        kdtree._PARALLEL_SPLIT_ROWS = saved
    left, right = tree.bounds[1:-1:2], tree.bounds[2::2]
    assert np.array_equal(left[:, 1], right[:, 0])  # children share their parent's rows
    assert np.array_equal(np.sort(tree.order), np.arange(n))
    internal = np.arange(tree.axes.size - (1 << tree.depth))
    axis = tree.axes[internal]
    assert np.all(tree.boxes[2 * internal + 1, 3 + axis] <= tree.boxes[2 * internal + 2, axis])
    indices, squared = tree.query(queries, k=k)
    expected_indices, expected_squared = _brute_force(points, queries, k)
    assert np.array_equal(indices, expected_indices)
    assert np.array_equal(squared, expected_squared)


def test_a_large_tree_splits_its_top_levels_on_every_thread() -> None:
    rng = np.random.default_rng(5)
    points = (rng.normal(0.0, 10.0, (300_000, 3)) * [1.0, 1.0, 0.1]).astype(np.float32)
    queries = points[::997]
    trees = {}
    for n_threads in (1, 4):
        with thread_limit(n_threads):
            trees[n_threads] = KdTree(points)
    one, four = trees[1], trees[4]
    sizes = np.diff(four.bounds, axis=1)[:, 0]
    assert not np.array_equal(one.bounds, four.bounds)  # the root split about a pivot
    assert 0.25 <= sizes[1] / points.shape[0] <= 0.75
    assert all(
        np.array_equal(a, b)
        for a, b in zip(one.query(queries, k=9), four.query(queries, k=9), strict=True)
    )
    expected = _brute_force(points, queries[:40], 9)
    assert np.array_equal(four.query(queries[:40], k=9)[0], expected[0])


def test_results_do_not_depend_on_the_thread_count() -> None:
    rng = np.random.default_rng(3)
    points = np.round(rng.random((20_000, 3)) * 50, 1).astype(np.float32)
    with thread_limit(1):
        one = KdTree(points).query(points, k=11)
    with thread_limit(4):
        four = KdTree(points).query(points, k=11)
    assert all(np.array_equal(a, b) for a, b in zip(one, four, strict=True))


@pytest.mark.parametrize("n", [1, 40, 5_000, 16_000, 70_000])
def test_every_node_holds_its_rows_on_any_number_of_threads(n: int) -> None:
    """Nodes split level by level, then subtrees taken whole by threads as they come
    free: every node's box holds its rows exactly, children split its rows along its axis
    (the lower child's rows not above the upper's), and below the size at which a top
    node is split on every thread (about a pivot) the tree is the same arrays however many
    threads built it."""
    from semantic3d.spatial.kdtree import _PARALLEL_SPLIT_ROWS

    rng = np.random.default_rng(n)
    points = np.round(rng.normal(size=(n, 3)), 1).astype(np.float32)  # with duplicates
    trees = []
    for threads in (1, 2, 3, 5):
        with thread_limit(threads):
            tree = KdTree(points)
        arrays = (tree._sorted, tree.order, tree.bounds, tree.boxes, tree.axes)
        trees.append(arrays)
        ordered, order, bounds, boxes, axes = arrays
        np.testing.assert_array_equal(ordered, points[order])
        np.testing.assert_array_equal(np.sort(order), np.arange(n))
        leaves = bounds[(1 << tree.depth) - 1 :]
        assert leaves[0, 0] == 0 and leaves[-1, 1] == n
        np.testing.assert_array_equal(leaves[1:, 0], leaves[:-1, 1])
        for node in range(bounds.shape[0]):
            start, stop = bounds[node]
            if stop > start:
                rows = ordered[start:stop].astype(np.float64)
                np.testing.assert_array_equal(boxes[node, :3], rows.min(axis=0))
                np.testing.assert_array_equal(boxes[node, 3:], rows.max(axis=0))
            if 2 * node + 2 < bounds.shape[0]:
                low, high = bounds[2 * node + 1], bounds[2 * node + 2]
                assert low[0] == start and low[1] == high[0] and high[1] == stop
                if low[1] > low[0] and high[1] > high[0]:
                    axis = axes[node]
                    assert (
                        ordered[low[0] : low[1], axis].max()
                        <= ordered[high[0] : high[1], axis].min()
                    )
    if n < _PARALLEL_SPLIT_ROWS:
        for other in trees[1:]:
            for a, b in zip(trees[0], other, strict=True):
                np.testing.assert_array_equal(a, b)


def test_bad_shapes_and_k_are_refused() -> None:
    tree = KdTree(np.zeros((3, 3), np.float32))
    with pytest.raises(ShapeError, match=r"expected \(n, 3\)"):
        KdTree(np.zeros((3, 2)))
    with pytest.raises(ShapeError, match=r"k: expected 1..3, found 4"):
        tree.query(np.zeros((1, 3), np.float32), k=4)
    with pytest.raises(ShapeError, match=r"queries: expected \(m, 3\)"):
        tree.query(np.zeros(3, np.float32), k=1)
