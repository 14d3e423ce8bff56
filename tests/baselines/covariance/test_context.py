"""Context steps: voxel-mean smoothing and alpha-expansion of a Potts energy."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from semantic3d.baselines.covariance.context import (
    alpha_expansion,
    knn_edges,
    potts_energy,
    smooth_probabilities,
    unary_costs,
)
from semantic3d.core.errors import ConfigError, ShapeError


def test_smoothing_mixes_each_row_with_its_voxel_means() -> None:
    proba = np.array([[1.0, 0.0], [0.0, 1.0], [0.5, 0.5]])
    level_a = np.array([0, 0, 1])  # rows 0 and 1 share a voxel
    level_b = np.array([0, 0, 0])
    one = smooth_probabilities(proba, [level_a], weight=0.5)
    np.testing.assert_allclose(one, [[0.75, 0.25], [0.25, 0.75], [0.5, 0.5]])
    two = smooth_probabilities(proba, [level_a, level_b], weight=1.0)
    mean_b = proba.mean(axis=0)
    expected = 0.5 * np.array([[0.5, 0.5], [0.5, 0.5], [0.5, 0.5]]) + 0.5 * mean_b
    np.testing.assert_allclose(two, expected)
    np.testing.assert_allclose(two.sum(axis=1), 1.0)
    np.testing.assert_array_equal(smooth_probabilities(proba, [level_a], weight=0.0), proba)


@pytest.mark.parametrize(
    ("proba", "ancestors", "weight", "error", "match"),
    [
        (np.ones(3), [np.zeros(3, np.int64)], 0.5, ShapeError, "expected \\(n_rows, n_classes\\)"),
        (np.ones((3, 2)), [np.zeros(2, np.int64)], 0.5, ShapeError, "expected \\(3,\\) per level"),
        (np.ones((3, 2)), [np.zeros(3, np.int64)], 1.5, ConfigError, "weight: expected a value"),
    ],
)
def test_smoothing_rejects_bad_input(proba, ancestors, weight, error, match) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(error, match=match):
        smooth_probabilities(proba, ancestors, weight=weight)


def test_knn_edges_are_unique_undirected_pairs() -> None:
    xyz = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [10, 0, 0], [10, 0, 0]])
    edges = knn_edges(xyz, k=1)
    assert np.all(edges[:, 0] < edges[:, 1])
    assert len({tuple(e) for e in edges}) == edges.shape[0]
    assert {(3, 4), (0, 1)} <= {tuple(e) for e in edges}
    assert knn_edges(xyz[:1], k=4).shape == (0, 2)


def test_alpha_expansion_lowers_the_energy_to_the_optimum_of_small_graphs() -> None:
    rng = np.random.default_rng(0)
    for _ in range(30):
        unary = rng.random((6, 3)) * 2
        pairs = [(i, j) for i in range(6) for j in range(i + 1, 6) if rng.random() < 0.5]
        edges = np.array(pairs, np.int64).reshape(-1, 2)
        weight = float(rng.random() * 1.5)
        labels = alpha_expansion(unary, edges, weight=weight, max_sweeps=10)
        start = potts_energy(unary, edges, unary.argmin(axis=1), weight=weight)
        found = potts_energy(unary, edges, labels, weight=weight)
        best = min(
            potts_energy(unary, edges, np.array(c), weight=weight)
            for c in itertools.product(range(3), repeat=6)
        )
        assert found <= start + 1e-12
        assert found <= 2 * best + 1e-12  # the Potts bound of alpha-expansion
        assert found == pytest.approx(best)  # exact on these small graphs


def test_alpha_expansion_cleans_isolated_noise_and_keeps_row_order() -> None:
    # A chain of 200 nodes, left half class 0, right half class 1, with flipped nodes.
    n = 200
    truth = (np.arange(n) >= n // 2).astype(np.int64)
    rng = np.random.default_rng(1)
    noisy = truth.copy()
    flipped = rng.choice(n, size=20, replace=False)
    noisy[flipped] = 1 - noisy[flipped]
    proba = np.full((n, 2), 0.3)
    proba[np.arange(n), noisy] = 0.7
    edges = np.stack([np.arange(n - 1), np.arange(1, n)], axis=1)
    unary = unary_costs(proba)
    labels = alpha_expansion(unary, edges, weight=1.0)
    assert potts_energy(unary, edges, labels, weight=1.0) < potts_energy(
        unary, edges, noisy, weight=1.0
    )
    assert np.count_nonzero(labels != truth) < np.count_nonzero(noisy != truth)
    # Permuting the nodes permutes the labels: the result is in input order.
    order = rng.permutation(n)
    inverse = np.argsort(order)
    permuted = alpha_expansion(unary[order], inverse[edges], weight=1.0)
    np.testing.assert_array_equal(permuted, labels[order])
    np.testing.assert_array_equal(alpha_expansion(unary, edges, weight=0.0), noisy)


def test_alpha_expansion_rejects_bad_input() -> None:
    with pytest.raises(ShapeError, match="unary: expected \\(n, n_classes\\)"):
        alpha_expansion(np.ones(4), np.empty((0, 2), np.int64), weight=1.0)
    with pytest.raises(ConfigError, match="weight: expected >= 0"):
        alpha_expansion(np.ones((4, 2)), np.empty((0, 2), np.int64), weight=-1.0)
    # the compiled loop trusts its indices: out-of-range ones are refused before it runs
    with pytest.raises(ShapeError, match=r"edges: expected pairs of two different nodes in 0\.\.3"):
        alpha_expansion(np.ones((4, 2)), np.array([[0, 4]]), weight=1.0)
    with pytest.raises(ShapeError, match="edges: expected pairs of two different nodes"):
        alpha_expansion(np.ones((4, 2)), np.array([[2, 2]]), weight=1.0)
    with pytest.raises(ShapeError, match=r"labels: expected columns in 0\.\.1"):
        alpha_expansion(np.ones((4, 2)), np.array([[0, 1]]), weight=1.0, labels=np.full(4, 2))
    with pytest.raises(ShapeError, match="labels: expected \\(4,\\)"):
        alpha_expansion(np.ones((4, 2)), np.array([[0, 1]]), weight=1.0, labels=np.zeros(3))


def _numpy_undirected_edges(neighbours: np.ndarray) -> np.ndarray:
    """The edges as the numpy expression the compiled kernel replaced computes them."""
    n, k = neighbours.shape
    first = np.repeat(np.arange(n, dtype=np.int64), k)
    second = neighbours.ravel().astype(np.int64)
    mutual = (neighbours[second] == first[:, None]).any(axis=1)
    keep = (first != second) & ((first < second) | ~mutual)
    low, high = first[keep], second[keep]
    return np.stack([np.minimum(low, high), np.maximum(low, high)], axis=1)


@pytest.mark.parametrize("seed", range(5))
def test_compiled_edges_equal_the_numpy_expression(seed: int) -> None:
    from semantic3d.baselines.covariance._context_kernels import undirected_edges

    rng = np.random.default_rng(seed)
    n, k = int(rng.integers(2, 60)), int(rng.integers(1, 6))
    neighbours = rng.integers(0, n, size=(n, k)).astype(np.int64)
    neighbours[:, 0] = np.arange(n)  # a k-NN search lists the point itself first
    np.testing.assert_array_equal(undirected_edges(neighbours), _numpy_undirected_edges(neighbours))


@pytest.mark.parametrize("seed", range(5))
def test_move_graph_cuts_cost_the_energy_of_the_labels_they_give(seed: int) -> None:
    # For every assignment x of a small graph (x = 1: take alpha), the cut's capacity is
    # the Potts energy of the labels x gives, up to one constant: minimum cuts are then
    # exactly the best moves.
    from semantic3d.baselines.covariance._context_kernels import expansion_capacities

    rng = np.random.default_rng(seed)
    n, n_labels = 8, 3
    unary = unary_costs(rng.dirichlet(np.ones(n_labels), size=n))
    edges = knn_edges(rng.random((n, 3)), k=3)
    current = rng.integers(0, n_labels, n).astype(np.int64)
    weight = float(rng.random() * 5)
    first, second = np.ascontiguousarray(edges[:, 0]), np.ascontiguousarray(edges[:, 1])
    for alpha in range(n_labels):
        terminal, forward, backward = np.empty(n), np.empty(first.size), np.empty(first.size)
        expansion_capacities(
            unary, first, second, current, alpha, weight, terminal, forward, backward
        )
        assert np.all(forward >= 0) and np.all(backward >= 0)
        offsets = []
        for bits in itertools.product((False, True), repeat=n):
            x = np.array(bits)
            cut = np.maximum(terminal, 0)[x].sum() + np.maximum(-terminal, 0)[~x].sum()
            cut += forward[~x[first] & x[second]].sum() + backward[x[first] & ~x[second]].sum()
            labels = np.where(x, alpha, current)
            offsets.append(potts_energy(unary, edges, labels, weight=weight) - cut)
        np.testing.assert_allclose(offsets, offsets[0], atol=1e-9)


def test_neighbour_lists_give_the_graph_and_each_group_is_labelled_alone() -> None:
    from semantic3d.baselines.covariance.context import graph_edges, label_rows, label_rows_by_group

    rng = np.random.default_rng(3)
    n, k = 600, 8
    xyz = rng.random((n, 3)) * [30.0, 10.0, 2.0]
    proba = rng.dirichlet(np.ones(4) * 0.7, size=n)
    # each row's k + 2 nearest (itself first), as the features give them
    distance = np.linalg.norm(xyz[:, None] - xyz[None], axis=2)
    lists = np.argsort(distance, axis=1, kind="stable")[:, : k + 2]
    edges = graph_edges(n, None, n_neighbours=k, neighbours=lists)
    assert np.all(edges[:, 0] < edges[:, 1])
    assert {tuple(e) for e in edges} == {
        (min(i, int(j)), max(i, int(j))) for i in range(n) for j in lists[i, 1 : k + 1]
    }
    group = (xyz[:, 0] // 10).astype(np.int64)  # three tiles
    together = label_rows_by_group(proba, None, group, potts_weight=2.0, neighbours=lists)
    for tile in range(3):
        rows = np.flatnonzero(group == tile)
        local = np.full(n, -1)
        local[rows] = np.arange(rows.size)
        alone = label_rows(proba[rows], None, potts_weight=2.0, neighbours=local[lists[rows]])
        np.testing.assert_array_equal(together[rows], alone)
    assert np.any(together != proba.argmax(axis=1))
    # lists too short for the graph: positions are needed, and used
    short = lists[:, :4]
    with pytest.raises(ShapeError, match="need row positions or neighbour lists of 9 columns"):
        label_rows(proba, None, potts_weight=2.0, neighbours=short)
    np.testing.assert_array_equal(
        label_rows(proba, xyz, potts_weight=2.0, neighbours=short),
        label_rows(proba, xyz, potts_weight=2.0),
    )
    with pytest.raises(ShapeError, match=r"neighbours: expected rows in -1\.\.599"):
        label_rows(proba, None, potts_weight=2.0, neighbours=lists + n)


@settings(max_examples=40, deadline=None)
@given(
    n=st.integers(1, 9000),
    extra=st.integers(0, 3),
    n_groups=st.integers(1, 5),
    seed=st.integers(0, 2**16),
)
def test_a_groups_edges_are_its_own_edges_of_the_whole_graph_in_list_order(
    n: int, extra: int, n_groups: int, seed: int
) -> None:
    """Each group's edges, made in its own task, are exactly the whole graph's edges with
    both ends in the group, in the whole graph's order, numbered within the group."""
    from semantic3d.baselines.covariance._context_kernels import group_edges, undirected_edges

    rng = np.random.default_rng(seed)
    width = 5
    lists = rng.integers(-1, n, (n, width + extra))
    lists[:, 0] = np.arange(n)  # each row first, as the features give them
    group = np.sort(rng.integers(0, n_groups, n)) if seed % 2 else rng.integers(0, n_groups, n)
    order = np.argsort(group, kind="stable")
    bounds = np.searchsorted(group[order], np.arange(n_groups + 1))
    local = np.empty(n, np.int64)
    local[order] = np.arange(n) - np.repeat(bounds[:-1], np.diff(bounds))

    whole = undirected_edges(np.ascontiguousarray(lists[:, :width]))
    for number in range(n_groups):
        rows = order[bounds[number] : bounds[number + 1]]
        edges = group_edges(lists, width, group, local, rows, number)
        own = whole[(group[whole[:, 0]] == number) & (group[whole[:, 1]] == number)]
        np.testing.assert_array_equal(edges, local[own].reshape(-1, 2))


@settings(max_examples=40, deadline=None)
@given(
    ids=st.lists(st.one_of(st.integers(0, 40), st.integers(-(2**40), 2**40)), min_size=1),
    runs=st.integers(1, 40),
)
def test_dense_groups_equal_numpy_unique(ids: list[int], runs: int) -> None:
    """Ids in any order, and in runs (rows gathered tile by tile)."""
    from semantic3d.baselines.covariance.context import _dense_groups

    row_group = np.repeat(np.array(ids, np.int64), runs)
    groups, inverse = _dense_groups(row_group)
    expected, expected_inverse = np.unique(row_group, return_inverse=True)
    np.testing.assert_array_equal(groups, expected)
    np.testing.assert_array_equal(inverse, expected_inverse.reshape(-1))
    assert inverse.dtype == np.int64


def test_a_large_group_is_cut_in_quadtree_squares_each_labelled_alone() -> None:
    """A tile of more rows than ``max_group_rows`` is labelled square by square (the
    quadtree of its rows' cells), each square as if alone, on any number of threads; a
    small tile, or no cap, is labelled whole."""
    from semantic3d.baselines.covariance.context import (
        GRAPH_CELL_DEPTH,
        label_rows,
        label_rows_by_group,
    )
    from semantic3d.core.threads import thread_limit
    from semantic3d.spatial.grid import TileGrid, quadtree_leaves

    rng = np.random.default_rng(5)
    n, k = 900, 8
    # a dense tile (0..16 m, most rows near its corner, as near a scanner) and a sparse one
    xyz = np.concatenate(
        [rng.gamma(1.5, 2.5, (700, 3)).clip(0, 15.9) * [1, 1, 0.2], rng.random((200, 3)) * 16]
    )
    xyz[700:, 0] += 16.0
    proba = rng.dirichlet(np.ones(4) * 0.7, size=n)
    distance = np.linalg.norm(xyz[:, None] - xyz[None], axis=2)
    lists = np.argsort(distance, axis=1, kind="stable")[:, : k + 2]
    grid = TileGrid(origin_xy=(0.0, 0.0), cell_size_m=0.25, cells_per_tile=64)
    tile = grid.tile_keys(xyz)[:, 0]
    cell = grid.cell_codes(xyz, depth=GRAPH_CELL_DEPTH)
    cap = 250  # the sparse tile (200 rows) stays whole

    def labelled(**options: object) -> np.ndarray:
        return label_rows_by_group(
            proba, None, tile, potts_weight=2.0, neighbours=lists, row_cell=cell, **options
        )

    split = labelled(max_group_rows=cap)
    leaves = quadtree_leaves(cell[:700], depth=GRAPH_CELL_DEPTH, max_count=cap)
    squares = np.unique(leaves)
    assert squares.size >= 700 // cap
    for first in squares.tolist():  # the dense tile: each square alone
        rows = np.flatnonzero(leaves == first)
        local = np.full(n, -1)
        local[rows] = np.arange(rows.size)
        alone = label_rows(proba[rows], None, potts_weight=2.0, neighbours=local[lists[rows]])
        np.testing.assert_array_equal(split[rows], alone)
    whole = labelled(max_group_rows=0)
    np.testing.assert_array_equal(split[700:], whole[700:])  # the sparse tile: whole
    np.testing.assert_array_equal(
        whole, label_rows_by_group(proba, None, tile, potts_weight=2.0, neighbours=lists)
    )
    assert not np.array_equal(split[:700], whole[:700])
    for threads in (1, 3):
        with thread_limit(threads):
            np.testing.assert_array_equal(labelled(max_group_rows=cap), split)
    with pytest.raises(ShapeError, match=r"row_cell: expected \(900,\), found \(3,\)"):
        label_rows_by_group(
            proba, None, tile, potts_weight=2.0, neighbours=lists, row_cell=cell[:3]
        )


def _split_groups_reference(
    inverse: np.ndarray, n_groups: int, cells: np.ndarray, max_rows: int
) -> tuple[np.ndarray, int]:
    """The split written with numpy, group by group (the definition)."""
    from semantic3d.baselines.covariance.context import GRAPH_CELL_DEPTH
    from semantic3d.spatial.grid import quadtree_leaves

    split = inverse.copy()
    for group in np.flatnonzero(np.bincount(inverse, minlength=n_groups) > max_rows).tolist():
        rows = np.flatnonzero(inverse == group)
        leaves = quadtree_leaves(cells[rows], depth=GRAPH_CELL_DEPTH, max_count=max_rows)
        present = np.zeros(1 << (2 * GRAPH_CELL_DEPTH), np.bool_)
        present[leaves] = True
        rank = (np.cumsum(present) - 1)[leaves]
        split[rows] = np.where(rank == 0, group, n_groups + rank - 1)
        n_groups += int(np.count_nonzero(present)) - 1
    return split, n_groups


@settings(max_examples=40, deadline=None)
@given(
    n=st.integers(1, 70_000),
    n_groups=st.integers(1, 6),
    max_rows=st.integers(1, 5000),
    spread=st.integers(0, 12),
    seed=st.integers(0, 2**16),
)
def test_groups_split_and_ordered_on_threads_equal_their_numpy_definition(
    n: int, n_groups: int, max_rows: int, spread: int, seed: int
) -> None:
    """The compiled split (every large group's squares counted in one pass on every
    thread) and the compiled grouping (a counting sort) give the numpy definitions: the
    same numbering of squares, the stable order of rows, the groups' bounds and each
    row's place in its group, on any number of threads."""
    from semantic3d.baselines.covariance.context import GRAPH_CELL_DEPTH, _split_groups
    from semantic3d.core.threads import thread_limit
    from semantic3d.spatial.voxels import group_order

    rng = np.random.default_rng(seed)
    inverse = rng.integers(0, n_groups, n)
    if seed % 3 == 0:  # a tile's rows: one group
        inverse[:] = 0
    # squares crowding into a corner (as near the scanner), up to every square
    cells = np.minimum(
        rng.geometric(1 / (1 + 2**spread), n) - 1, (1 << (2 * GRAPH_CELL_DEPTH)) - 1
    ).astype(np.uint16)
    split, count = _split_groups(inverse, n_groups, cells, max_rows)
    expected, expected_count = _split_groups_reference(inverse, n_groups, cells, max_rows)
    np.testing.assert_array_equal(split, expected)
    assert count == expected_count
    for threads in (1, 3):
        with thread_limit(threads):
            order, bounds, local = group_order(split, count)
        np.testing.assert_array_equal(order, np.argsort(split, kind="stable"))
        np.testing.assert_array_equal(bounds, np.searchsorted(split[order], np.arange(count + 1)))
        np.testing.assert_array_equal(local[order], np.arange(n) - bounds[split[order]])


def test_bad_squares_and_neighbour_rows_are_refused_in_one_line() -> None:
    from semantic3d.baselines.covariance.context import _checked_lists, _split_groups

    with pytest.raises(ShapeError, match=r"row_cell: expected squares in 0\.\.4095"):
        _split_groups(np.zeros(5, np.int64), 1, np.full(5, 4096, np.uint16), 2)
    with pytest.raises(ShapeError, match=r"row_cell: expected squares in 0\.\.4095"):
        _split_groups(np.zeros(5, np.int64), 1, np.full(5, -1, np.int64), 2)
    lists = np.tile(np.arange(3), (4, 1))
    np.testing.assert_array_equal(_checked_lists(lists, 4, 2), lists)
    lists[3, 1] = 4
    with pytest.raises(ShapeError, match=r"neighbours: expected rows in -1\.\.3"):
        _checked_lists(lists, 4, 2)
    lists[3, 1] = -2
    with pytest.raises(ShapeError, match=r"neighbours: expected rows in -1\.\.3"):
        _checked_lists(lists, 4, 2)
    lists[3, 2] = 9  # past the columns the graph uses: not checked
    lists[3, 1] = 0
    np.testing.assert_array_equal(_checked_lists(lists, 4, 1), lists)
