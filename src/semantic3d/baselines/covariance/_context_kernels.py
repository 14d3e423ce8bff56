"""Compiled bookkeeping of the context step: the k-NN graph's edges and each expansion move's
graph capacities.

Hand-written because the numpy expressions they replaced made ~15 passes over the edge
arrays per move (fancy indexing, three ``bincount``\\ s, temporaries) and an
``(n * (k + 1), k + 1)`` comparison table for the edges; together they cost more than the
max-flow itself. Each kernel is one or two passes.
"""

from __future__ import annotations

from typing import Any

import numba as nb
import numpy as np


@nb.njit(cache=True, nogil=True)
def undirected_edges(neighbours: np.ndarray) -> np.ndarray:  # pragma: no cover - compiled
    """``(n_edges, 2)`` int64 pairs ``(min, max)`` from ``(n, k)`` neighbour lists that may
    hold the point itself and ``-1`` for absent entries: ``(i, j)`` is kept from ``i``'s
    list when ``i < j`` or when ``i`` is not in ``j``'s list (each undirected edge once), in
    row-major list order."""
    n, k = neighbours.shape
    out = np.empty((n * k, 2), np.int64)
    count = 0
    for i in range(n):
        for slot in range(k):
            j = np.int64(neighbours[i, slot])
            if j == i or j < 0:
                continue
            keep = True
            if j < i:
                for other in range(k):
                    if neighbours[j, other] == i:
                        keep = False
                        break
            if keep:
                out[count, 0] = min(i, j)
                out[count, 1] = max(i, j)
                count += 1
    return out[:count].copy()


@nb.njit(cache=True, nogil=True, inline="always")
def _kept(neighbours: np.ndarray, width: Any, i: Any, j: Any) -> bool:  # pragma: no cover
    """Whether ``undirected_edges`` keeps ``(i, j)`` from ``i``'s list."""
    if j == i or j < 0:
        return False
    if j < i:
        for other in range(width):
            if neighbours[j, other] == i:
                return False
    return True


@nb.njit(cache=True, nogil=True)
def group_edges(
    neighbours: np.ndarray,
    width: int,
    group: np.ndarray,
    local: np.ndarray,
    rows: np.ndarray,
    number: int,
) -> np.ndarray:  # pragma: no cover - compiled
    """Group ``number``'s own edges: :func:`undirected_edges` of the first ``width``
    columns of ``neighbours`` whose two ends are both in the group (``rows``, its rows
    ascending, so in row-major list order), as ``local`` row numbers. Made in the group's
    task: no edge array of every group at once."""
    out = np.empty((rows.shape[0] * width, 2), np.int64)
    count = 0
    for r in range(rows.shape[0]):
        i = np.int64(rows[r])
        for slot in range(width):
            j = np.int64(neighbours[i, slot])
            if _kept(neighbours, width, i, j) and group[j] == number:
                low, high = (i, j) if i < j else (j, i)
                out[count, 0] = local[low]
                out[count, 1] = local[high]
                count += 1
    return out[:count].copy()


@nb.njit(cache=True, nogil=True, inline="always")
def _edge_move(
    li: int, lj: int, alpha: int, weight: float, half: float
) -> tuple[float, float, float]:  # pragma: no cover - compiled
    """An edge's part of an expansion move between ends labelled ``li`` and ``lj``: its
    capacity both ways, and what it takes off each end's terminal capacity."""
    if li == lj:
        return (weight if li != alpha else 0.0), 0.0, 0.0
    if li == alpha:
        return 0.0, 0.0, weight
    if lj == alpha:
        return 0.0, weight, 0.0
    return half, half, half


@nb.njit(cache=True, nogil=True)
def expansion_capacities(
    unary: np.ndarray,
    first: np.ndarray,
    second: np.ndarray,
    current: np.ndarray,
    alpha: int,
    weight: float,
    terminal: np.ndarray,
    forward: np.ndarray,
    backward: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """The binary graph of one alpha-expansion move (x = 1: the node takes ``alpha``).

    Writes ``terminal[i]``, the cost of ``x_i = 1`` minus that of ``x_i = 0`` (positive:
    the capacity from the source, negative: minus the capacity to the sink), and the
    capacities of edge ``e`` from ``first[e]`` to ``second[e]`` (``forward``, paid when
    ``first`` keeps and ``second`` takes alpha) and back (``backward``).

    Each edge's Potts term is split symmetrically (Kolmogorov & Zabih 2004 allow any split
    with the same energy): two ends with one label other than alpha get ``weight`` both
    ways and nothing on the terminals; an end already labelled alpha makes the other end's
    switch ``weight`` cheaper; two different labels, neither alpha, get ``weight / 2``
    both ways and each end's switch ``weight / 2`` cheaper. The first split tried (all of
    the term on the edge's first node, ``2 * weight`` one way) gave the same cuts but drove
    ~50 000 augmenting paths through a 96 000-voxel scan per move, and took twice as long.
    """
    edges = np.arange(first.size)  # each edge's capacity, the same both ways
    expansion_arcs(unary, first, second, current, alpha, weight, terminal, edges, edges, forward)
    backward[:] = forward


@nb.njit(cache=True, nogil=True)
def expansion_arcs(
    unary: np.ndarray,
    first: np.ndarray,
    second: np.ndarray,
    current: np.ndarray,
    alpha: int,
    weight: float,
    terminal: np.ndarray,
    forward_arc: np.ndarray,
    backward_arc: np.ndarray,
    residual: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """:func:`expansion_capacities` written straight onto the arcs of the move's graph:
    edge ``e``'s capacities go to ``residual[forward_arc[e]]`` and
    ``residual[backward_arc[e]]`` (one pass over the edges, not two)."""
    for i in range(unary.shape[0]):
        terminal[i] = unary[i, alpha] - unary[i, current[i]]
    half = 0.5 * weight
    for e in range(first.size):
        i = first[e]
        j = second[e]
        capacity, off_i, off_j = _edge_move(current[i], current[j], alpha, weight, half)
        terminal[i] -= off_i  # x - 0.0 is x: the same sums as subtracting only the parts
        terminal[j] -= off_j
        residual[forward_arc[e]] = capacity
        residual[backward_arc[e]] = capacity


@nb.njit(cache=True, nogil=True)
def count_cut_edges(
    first: np.ndarray, second: np.ndarray, labels: np.ndarray
) -> int:  # pragma: no cover - compiled
    """Edges whose two ends have different labels."""
    count = 0
    for e in range(first.size):
        if labels[first[e]] != labels[second[e]]:
            count += 1
    return count


_GROUP_BLOCK_ROWS = 1 << 15  # the least rows a thread counts on its own


_GROUP_COUNTS = 1 << 21  # the most counts the blocks hold together


@nb.njit(cache=True, nogil=True)
def _row_blocks(n: int, n_threads: int, width: int) -> tuple[int, int]:  # pragma: no cover
    """Blocks of consecutive rows counted apart (each with ``width`` counts): their number
    and rows per block."""
    n_blocks = max(1, min(4 * n_threads, n // _GROUP_BLOCK_ROWS, _GROUP_COUNTS // width))
    return n_blocks, -(-n // n_blocks)


@nb.njit(cache=True, nogil=True, parallel=True)
def large_group_codes(
    inverse: np.ndarray,
    slot_of_group: np.ndarray,
    n_large: int,
    codes: np.ndarray,
    n_codes: int,
    n_threads: int,
) -> np.ndarray:  # pragma: no cover - compiled
    """``(n_large, n_codes)`` rows per code of the groups with a slot (``slot_of_group[g]``
    >= 0), counted on every thread in blocks of rows."""
    n = inverse.shape[0]
    n_blocks, per_block = _row_blocks(n, n_threads, max(1, n_large * n_codes))
    partial = np.zeros((n_blocks, n_large, n_codes), np.int64)
    for block in nb.prange(n_blocks):
        for i in range(block * per_block, min(n, (block + 1) * per_block)):
            slot = slot_of_group[inverse[i]]
            if slot >= 0:
                partial[block, slot, codes[i]] += 1
    counts = np.zeros((n_large, n_codes), np.int64)
    for block in range(n_blocks):
        counts += partial[block]
    return counts


@nb.njit(cache=True, nogil=True, parallel=True)
def split_rows(
    inverse: np.ndarray, slot_of_group: np.ndarray, codes: np.ndarray, code_group: np.ndarray
) -> np.ndarray:  # pragma: no cover - compiled
    """Each row's group after the split: ``code_group[slot, code]`` for rows of a group
    with a slot, its own group otherwise."""
    out = np.empty(inverse.shape[0], np.int64)
    for i in nb.prange(inverse.shape[0]):
        slot = slot_of_group[inverse[i]]
        out[i] = inverse[i] if slot < 0 else code_group[slot, codes[i]]
    return out


@nb.njit(cache=True, nogil=True, parallel=True)
def column_range(lists: np.ndarray, width: int) -> tuple[Any, Any]:  # pragma: no cover
    """Smallest and largest entry of the first ``width`` columns, reduced on every thread."""
    low: Any = np.iinfo(np.int64).max
    high: Any = np.iinfo(np.int64).min
    for i in nb.prange(lists.shape[0]):
        for column in range(width):
            value = np.int64(lists[i, column])
            low = min(low, value)
            high = max(high, value)
    return low, high


@nb.njit(cache=True, nogil=True, parallel=True)
def all_equal(values: np.ndarray) -> bool:  # pragma: no cover - compiled
    """Whether every value equals the first (checked on every thread)."""
    first = values[0]
    differ = 0
    for i in nb.prange(values.shape[0]):
        if values[i] != first:
            differ += 1
    return differ == 0


@nb.njit(cache=True, nogil=True, parallel=True)
def last_points(point_row: np.ndarray, n_rows: int) -> np.ndarray:  # pragma: no cover
    """The last point of every row (``-1`` for a row without points): where numpy's
    ``row[point_row] = ...`` leaves each row's value from. On every thread: each pass
    raises a row's point to any later point of the row seen, until a pass raises none
    (a row's value is then the largest of its points: passes race only to raise it, and
    end in the same values whatever the threads)."""
    last = np.full(n_rows, -1, np.int64)
    raised = 1
    while raised:
        raised = 0
        for i in nb.prange(point_row.shape[0]):
            row = point_row[i]
            if last[row] < i:
                last[row] = i
                raised += 1
    return last
