"""Context for the covariance baseline: per-row class probabilities made spatially coherent.

Two ways to use the neighbourhood of a row (a level-0 voxel) once the classifier has given
every row its class probabilities:

- :func:`smooth_probabilities` mixes each row's probabilities with their mean over the
  pyramid voxel that contains it at one or more coarser levels (cheap, and exact under
  tiling: tiles hold whole coarsest voxels, hence whole voxels of every level);
- :func:`alpha_expansion` labels a graph (k nearest neighbours, :func:`knn_edges`) by
  minimising a Potts energy, ``sum_i -log p_i(l_i) + weight * sum_(i,j) [l_i != l_j]``,
  with alpha-expansion moves (Boykov, Veksler & Zabih 2001), each move an exact binary
  cut (Boykov-Kolmogorov max-flow, compiled: :mod:`._graph_cut`).

A scan's graph is cut tile by tile (:func:`label_rows_by_group`), and a tile's graph of
more than ``max_group_rows`` rows in quadtree squares of at most that many: no edge joins
two groups, so the groups are cut at the same time, and every group's labels are those it
gets alone, whatever the threads.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from semantic3d.core.errors import ConfigError, ShapeError
from semantic3d.core.threads import (
    map_in_threads,
    serial_section,
    take_free_threads,
    thread_budget,
)
from semantic3d.core.timeline import span
from semantic3d.spatial.grid import quadtree_leaf_table

__all__ = [
    "GRAPH_CELL_DEPTH",
    "alpha_expansion",
    "graph_edges",
    "knn_edges",
    "label_rows",
    "label_rows_by_group",
    "last_points",
    "lists_suffice",
    "potts_energy",
    "row_centroids",
    "smooth_probabilities",
    "unary_costs",
]

_EPS = 1e-6

GRAPH_CELL_DEPTH = 6
"""Depth of the rows' square codes (``row_cell``) that cut a large tile's graph: squares of
a 64th of the tile's edge at the finest (40 cm for the default 25.6 m tiles)."""


def smooth_probabilities(
    proba: NDArray[np.floating],
    ancestors: Sequence[NDArray[np.int64]],
    *,
    weight: float = 0.5,
) -> NDArray[np.float64]:
    """Mix each row's probabilities with their mean over coarser voxels.

    Args:
        proba: ``(n_rows, n_classes)`` class probabilities.
        ancestors: for each coarser level, ``(n_rows,)`` index of the voxel holding each
            row (:meth:`~semantic3d.features.pyramid.VoxelPyramid.ancestors`).
        weight: share of the voxel means (averaged over the levels) in the result.

    Returns:
        ``(n_rows, n_classes)``: ``(1 - weight) * proba + weight * mean of the voxel means``.
    """
    proba = np.asarray(proba, dtype=np.float64)
    if proba.ndim != 2:
        raise ShapeError(f"proba: expected (n_rows, n_classes), found {proba.shape}")
    if not 0.0 <= weight <= 1.0:
        raise ConfigError(f"weight: expected a value in [0, 1], found {weight}")
    if not ancestors or weight == 0.0:
        return np.array(proba, dtype=np.float64)
    context = np.zeros_like(proba)
    for index in ancestors:
        if index.shape != (proba.shape[0],):
            raise ShapeError(
                f"ancestors: expected ({proba.shape[0]},) per level, found {index.shape}"
            )
        count = np.bincount(index).astype(np.float64)
        sums = np.stack(
            [np.bincount(index, proba[:, c], minlength=count.size) for c in range(proba.shape[1])],
            axis=1,
        )
        context += (sums / np.maximum(count, 1.0)[:, None])[index]
    result: NDArray[np.float64] = (1.0 - weight) * proba + (weight / len(ancestors)) * context
    return result


def knn_edges(xyz: NDArray[np.floating], *, k: int = 8) -> NDArray[np.int64]:
    """Undirected edges ``(n_edges, 2)`` joining every point to its ``k`` nearest others,
    each edge once, as ``(min, max)``."""
    from semantic3d.baselines.covariance._context_kernels import undirected_edges
    from semantic3d.spatial.kdtree import KdTree

    xyz = np.asarray(xyz, dtype=np.float64)
    n = xyz.shape[0]
    k = min(k, n - 1)
    if k < 1:
        return np.empty((0, 2), np.int64)
    local = (xyz - xyz.min(axis=0)).astype(np.float32)
    found, _ = KdTree(local).query(local, k=k + 1)
    # Keep (i, j) once: from i's list when i < j, or when i is not in j's list.
    edges: NDArray[np.int64] = undirected_edges(
        np.ascontiguousarray(found, dtype=np.int64).reshape(n, k + 1)
    )
    return edges


def unary_costs(proba: NDArray[np.floating]) -> NDArray[np.float64]:
    """``-log`` of the probabilities, floored at 1e-6 so no label is impossible."""
    cost: NDArray[np.float64] = -np.log(np.maximum(np.asarray(proba, np.float64), _EPS))
    return cost


def potts_energy(
    unary: NDArray[np.floating],
    edges: NDArray[np.int64],
    labels: NDArray[np.integer],
    *,
    weight: float,
) -> float:
    """``sum_i unary[i, labels[i]] + weight * (edges whose ends differ)``."""
    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    return _energy(
        np.asarray(unary, dtype=np.float64),
        np.ascontiguousarray(edges[:, 0]),
        np.ascontiguousarray(edges[:, 1]),
        np.asarray(labels, dtype=np.int64),
        weight,
    )


def _energy(
    unary: NDArray[np.float64],
    first: NDArray[np.int64],
    second: NDArray[np.int64],
    labels: NDArray[np.int64],
    weight: float,
) -> float:
    from semantic3d.baselines.covariance._context_kernels import count_cut_edges

    data = float(np.take_along_axis(unary, labels[:, None], axis=1).sum())
    cut = int(count_cut_edges(first, second, labels)) if first.size else 0
    return data + weight * cut


def alpha_expansion(
    unary: NDArray[np.floating],
    edges: NDArray[np.int64],
    *,
    weight: float,
    labels: NDArray[np.integer] | None = None,
    max_sweeps: int = 3,
) -> NDArray[np.int64]:
    """Column indices minimising the Potts energy (:func:`potts_energy`) by alpha-expansion.

    Args:
        unary: ``(n, n_classes)`` cost of each label at each node (:func:`unary_costs`).
        edges: ``(n_edges, 2)`` node pairs.
        weight: cost of an edge whose ends take different labels (>= 0).
        labels: start (default: the cheapest label of each node).
        max_sweeps: passes over all labels; stops early when a pass changes nothing.

    Each move is solved exactly, so the energy never rises; the result is within a factor
    2 of the optimum for the Potts model. The loop runs compiled and without the GIL
    (:func:`~semantic3d.baselines.covariance._graph_cut.expand_labels`), so scans labelled on
    several threads cut their graphs at the same time.
    """
    unary = np.asarray(unary, dtype=np.float64)
    if unary.ndim != 2:
        raise ShapeError(f"unary: expected (n, n_classes), found {unary.shape}")
    if weight < 0:
        raise ConfigError(f"weight: expected >= 0, found {weight}")
    n = unary.shape[0]
    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    current = (
        np.argmin(unary, axis=1).astype(np.int64)
        if labels is None
        else np.asarray(labels, dtype=np.int64).copy()
    )
    if current.shape != (n,):
        raise ShapeError(f"labels: expected ({n},), found {current.shape}")
    if n == 0 or weight == 0 or edges.shape[0] == 0:
        return current
    if edges.min() < 0 or edges.max() >= n or np.any(edges[:, 0] == edges[:, 1]):
        raise ShapeError(f"edges: expected pairs of two different nodes in 0..{n - 1}")
    if current.min() < 0 or current.max() >= unary.shape[1]:
        raise ShapeError(f"labels: expected columns in 0..{unary.shape[1] - 1}")
    from semantic3d.baselines.covariance._graph_cut import expand_labels, index_type

    expanded: NDArray[np.int64] = expand_labels(
        np.ascontiguousarray(unary),
        np.ascontiguousarray(edges[:, 0]),
        np.ascontiguousarray(edges[:, 1]),
        current,
        float(weight),
        int(max_sweeps),
        index_type(n, edges.shape[0]),
    )
    return expanded


def row_centroids(
    xyz: NDArray[np.floating], point_row: NDArray[np.int64], n_rows: int
) -> NDArray[np.float64]:
    """``(n_rows, 3)`` mean position of the points of every row (a row's points are
    those with ``point_row == row``; a row without points gets the origin)."""
    if xyz.shape != (point_row.shape[0], 3):
        raise ShapeError(f"xyz: expected ({point_row.shape[0]}, 3), found {xyz.shape}")
    count = np.maximum(np.bincount(point_row, minlength=n_rows), 1).astype(np.float64)
    return np.stack(
        [np.bincount(point_row, xyz[:, axis], minlength=n_rows) / count for axis in range(3)],
        axis=1,
    )


def label_rows(
    proba: NDArray[np.floating],
    row_xyz: NDArray[np.floating] | None,
    *,
    potts_weight: float,
    n_neighbours: int = 8,
    max_sweeps: int = 1,
    neighbours: NDArray[np.int64] | None = None,
) -> NDArray[np.int64]:
    """Column of ``proba`` chosen for every row: the most probable class, then (with
    ``potts_weight > 0``) alpha-expansion over the graph joining every row to its
    ``n_neighbours`` nearest rows: the first ``n_neighbours + 1`` columns of
    ``neighbours`` (each row's nearest rows, itself first, ``-1`` where absent; see
    :attr:`~semantic3d.features.multiscale.FeatureTable.neighbours`) when it has them,
    else a k-NN search over ``row_xyz``."""
    proba = np.asarray(proba)
    if potts_weight <= 0 or proba.shape[0] < 2:
        return np.argmax(proba, axis=1).astype(np.int64)
    edges = graph_edges(proba.shape[0], row_xyz, n_neighbours=n_neighbours, neighbours=neighbours)
    return alpha_expansion(unary_costs(proba), edges, weight=potts_weight, max_sweeps=max_sweeps)


def graph_edges(
    n_rows: int,
    row_xyz: NDArray[np.floating] | None,
    *,
    n_neighbours: int,
    neighbours: NDArray[np.int64] | None = None,
) -> NDArray[np.int64]:
    """The context graph's undirected edges ``(n_edges, 2)`` over ``n_rows`` rows (see
    :func:`label_rows`)."""
    from semantic3d.baselines.covariance._context_kernels import undirected_edges

    if lists_suffice(neighbours, n_neighbours):
        assert neighbours is not None
        lists = _checked_lists(neighbours, n_rows, n_neighbours)
        edges: NDArray[np.int64] = undirected_edges(
            np.ascontiguousarray(lists[:, : n_neighbours + 1])
        )
        return edges
    if row_xyz is None:
        raise ShapeError(
            f"context graph: {n_neighbours} neighbours per row need row positions or "
            f"neighbour lists of {n_neighbours + 1} columns"
        )
    if row_xyz.shape != (n_rows, 3):
        raise ShapeError(f"row_xyz: expected ({n_rows}, 3), found {row_xyz.shape}")
    return knn_edges(row_xyz, k=n_neighbours)


def _checked_lists(
    neighbours: NDArray[np.int64], n_rows: int, n_neighbours: int
) -> NDArray[np.int64]:
    """``neighbours`` as C-ordered int64, its first ``n_neighbours + 1`` columns checked."""
    if neighbours.shape[0] != n_rows:
        raise ShapeError(f"neighbours: expected {n_rows} rows, found {neighbours.shape[0]}")
    from semantic3d.baselines.covariance._context_kernels import column_range

    lists = np.ascontiguousarray(neighbours, dtype=np.int64)
    width = min(n_neighbours + 1, lists.shape[1])
    if lists.shape[0] and width:
        low, high = column_range(lists, width)
        if high >= n_rows or low < -1:
            raise ShapeError(f"neighbours: expected rows in -1..{n_rows - 1}")
    return lists


def _dense_groups(row_group: NDArray[np.int64]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """``np.unique(row_group, return_inverse=True)`` in linear time where it can: ids that
    come in long runs (rows gathered tile by tile) by their runs, small non-negative ids by
    marking a table; sorting only otherwise."""
    from semantic3d.baselines.covariance._context_kernels import all_equal

    n = row_group.size
    if n and all_equal(row_group):  # one group (a tile's rows): no pass to number them
        return row_group[:1].copy(), np.zeros(n, np.int64)
    change = np.flatnonzero(row_group[1:] != row_group[:-1]) + 1
    if change.size < n // 16:
        starts = np.concatenate(([0], change))
        groups, run_rank = np.unique(row_group[starts], return_inverse=True)
        lengths = np.diff(np.append(starts, n))
        return groups, np.repeat(run_rank.reshape(-1).astype(np.int64), lengths)
    low, high = int(row_group.min()), int(row_group.max())
    if low < 0 or high >= max(1 << 20, 4 * n):
        groups, inverse = np.unique(row_group, return_inverse=True)
        return groups, inverse.reshape(-1).astype(np.int64, copy=False)
    from semantic3d.features.multiscale import distinct_voxels  # a marked table, threaded

    return distinct_voxels(row_group)


def lists_suffice(neighbours: NDArray[np.int64] | None, n_neighbours: int) -> bool:
    """Whether neighbour lists (each row itself first) can name ``n_neighbours`` others per
    row. A scan of very few voxels has shorter lists; the context graph then comes from the
    rows' positions, whole or tiled alike."""
    return neighbours is not None and neighbours.ndim == 2 and neighbours.shape[1] > n_neighbours


def last_points(point_row: NDArray[np.int64], n_rows: int) -> NDArray[np.int64]:
    """The last of every row's points (``point_row`` the row of each point; -1 for a row
    without points), whose place a row takes: where numpy's ``row[point_row] = ...``
    leaves each row's value from. On every thread, the same for any threads."""
    from semantic3d.baselines.covariance._context_kernels import last_points as kernel

    last: NDArray[np.int64] = kernel(np.ascontiguousarray(point_row, dtype=np.int64), n_rows)
    return last


def label_rows_by_group(
    proba: NDArray[np.floating],
    row_xyz: NDArray[np.floating] | None,
    row_group: NDArray[np.int64],
    *,
    potts_weight: float,
    n_neighbours: int = 8,
    max_sweeps: int = 1,
    neighbours: NDArray[np.int64] | None = None,
    row_cell: NDArray[np.integer] | None = None,
    max_group_rows: int = 0,
) -> NDArray[np.int64]:
    """:func:`label_rows` run separately on every group of rows (``row_group``, e.g. the
    tile of each row): no edge joins two groups, so a scan labelled whole gives the same
    labels as the same scan labelled tile by tile. With ``row_cell`` (each row's square in
    its tile, :meth:`~semantic3d.spatial.grid.TileGrid.cell_codes` at
    :data:`GRAPH_CELL_DEPTH`) and ``max_group_rows`` > 0, a group of more rows is cut
    further into quadtree squares of at most that many (:func:`_split_groups`). Groups are
    labelled on the thread budget's threads at once (each group's labels are those it
    gets alone); one group alone on one thread, the others lent back
    (:func:`~semantic3d.core.threads.serial_section`)."""
    proba = np.asarray(proba)
    n = proba.shape[0]
    if row_group.shape != (n,):
        raise ShapeError(f"row_group: expected ({n},), found {row_group.shape}")
    if row_cell is not None and row_cell.shape != (n,):
        raise ShapeError(f"row_cell: expected ({n},), found {row_cell.shape}")
    if potts_weight <= 0 or n < 2:
        return np.argmax(proba, axis=1).astype(np.int64)
    groups, inverse = _dense_groups(np.asarray(row_group, np.int64))
    n_groups = groups.size
    if row_cell is not None and max_group_rows > 0:
        inverse, n_groups = _split_groups(inverse, n_groups, row_cell, max_group_rows)
    if n_groups <= 1:
        with serial_section():
            return label_rows(
                proba,
                row_xyz,
                potts_weight=potts_weight,
                n_neighbours=n_neighbours,
                max_sweeps=max_sweeps,
                neighbours=neighbours,
            )
    from semantic3d.baselines.covariance._context_kernels import group_edges
    from semantic3d.spatial.voxels import group_order

    result = np.empty(n, np.int64)
    # the rows group by group (each ascending), the groups' bounds, each row's place in
    # its group: one counting sort on the task's threads
    order, bounds, local = group_order(inverse, n_groups)
    lists = None
    if lists_suffice(neighbours, n_neighbours):
        assert neighbours is not None
        lists = _checked_lists(neighbours, n, n_neighbours)

    def label_group(number: int) -> NDArray[np.int64]:
        rows = order[bounds[number] : bounds[number + 1]]  # ascending: the group's order
        with span("cut square", rows=rows.size):
            if lists is None:
                return label_rows(
                    proba[rows],
                    None if row_xyz is None else row_xyz[rows],
                    potts_weight=potts_weight,
                    n_neighbours=n_neighbours,
                    max_sweeps=max_sweeps,
                )
            # the group's own edges, in their order, numbered within the group: made in
            # its task (the edges of a dense tile's every square at once were 16 bytes an
            # edge, about 7 edges a row)
            edges = group_edges(lists, n_neighbours + 1, inverse, local, rows, number)
            unary = unary_costs(proba[rows])  # in the group's task: on its thread
            return alpha_expansion(unary, edges, weight=potts_weight, max_sweeps=max_sweeps)

    threads = take_free_threads()  # in a map's last tasks: the threads the others left
    # groups cut at the same time (the cuts release the GIL); each group's labels alone.
    # The largest first: the last cut to end is then a small one, not the densest tile's
    # alone on one thread while the others wait (a twelfth of a 2 M-point scan's time).
    largest_first = np.argsort(-np.diff(bounds), kind="stable").tolist()
    with span("squares", groups=n_groups, threads=threads):
        for number, labels in zip(
            largest_first,
            map_in_threads(label_group, largest_first, name="s3d-graph-cut"),
            strict=True,
        ):
            result[order[bounds[number] : bounds[number + 1]]] = labels
    return result


def _split_groups(
    inverse: NDArray[np.int64],
    n_groups: int,
    row_cell: NDArray[np.integer],
    max_rows: int,
) -> tuple[NDArray[np.int64], int]:
    """Groups (``inverse``, numbered ``0..n_groups-1``) of more than ``max_rows`` rows cut
    into the quadtree squares of their rows' cells
    (:func:`~semantic3d.spatial.grid.quadtree_leaves`): a square of more rows is cut into
    its quadrants, down to the squares of :data:`GRAPH_CELL_DEPTH`. The first square keeps
    the group's number, the others are numbered after the groups. Depends only on each
    group's rows and cells."""
    from semantic3d.baselines.covariance._context_kernels import (
        column_range,
        large_group_codes,
        split_rows,
    )

    sizes = np.bincount(inverse, minlength=n_groups)
    large = np.flatnonzero(sizes > max_rows)
    if not large.size:
        return inverse, n_groups
    n_codes = 1 << (2 * GRAPH_CELL_DEPTH)
    cells = np.ascontiguousarray(row_cell)
    if cells.dtype != np.uint16:  # the squares' type; any other integers as int64
        cells = cells.astype(np.int64)
    if cells.size:
        low, high = column_range(cells.reshape(-1, 1), 1)
        if low < 0 or high >= n_codes:
            raise ShapeError(f"row_cell: expected squares in 0..{n_codes - 1}")
    slot_of_group = np.full(n_groups, -1, np.int64)
    slot_of_group[large] = np.arange(large.size)
    # every large group's rows per square, counted on every thread in one pass
    counts = large_group_codes(inverse, slot_of_group, large.size, cells, n_codes, thread_budget())
    code_group = np.empty((large.size, n_codes), np.int64)
    for slot, group in enumerate(large.tolist()):
        leaf = quadtree_leaf_table(counts[slot], depth=GRAPH_CELL_DEPTH, max_count=max_rows)
        present = np.zeros(n_codes, np.bool_)  # by code: no sort
        present[leaf[counts[slot] > 0]] = True
        rank = (np.cumsum(present) - 1)[leaf]
        code_group[slot] = np.where(rank == 0, group, n_groups + rank - 1)
        n_groups += int(np.count_nonzero(present)) - 1
    return split_rows(inverse, slot_of_group, cells, code_group), n_groups
