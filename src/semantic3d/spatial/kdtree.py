"""Exact k nearest neighbours of float32 points: a k-d tree built and searched on all cores.

Hand-written (numba) because the library it replaces here, pgeof's nanoflann search,
holds the GIL for the whole call, builds its tree on one thread and starts one thread
per core of the machine on every call whatever the process was asked to use: tiles of a
scan could not be searched at the same time and ``--threads`` could not cap it. This tree
is built level by level (a top level's few large nodes each split on every thread, the
next levels' nodes split in parallel), then subtree by subtree (each whole on one thread,
taken as threads come free), searched in parallel
over the queries, releases the GIL and runs on numba's threads (the package's budget,
:mod:`semantic3d.core.threads`).

Distances are squared and computed in float32 as ``(dx*dx + dy*dy) + dz*dz``, the
arithmetic of nanoflann's L2 metric, so the same points give the same distances. The
result of a query is a function of the point set alone: the ``k`` smallest
``(distance, index)`` pairs, ascending, whatever the tree's shape or the number of threads
(pruning keeps any node that could hold a tie).
"""

from __future__ import annotations

from typing import Any

import numba
import numpy as np
from numpy.typing import NDArray

from semantic3d.core.atomic import row_workers, take_row_block
from semantic3d.core.errors import ShapeError

__all__ = ["KdTree"]

LEAF_SIZE = 16
_QUERY_BLOCK = 256  # queries per parallel task (one heap and stack each)
_PRUNE_MARGIN = 1e-5  # relative: a node's float64 box distance vs float32 point distances
_PARALLEL_SPLIT_ROWS = 1 << 14
"""A node of a level with fewer nodes than threads is split on every thread from this
many rows on (fewer: each node on one thread, the nodes of a level in parallel)."""
_PIVOT_SAMPLE = 2048  # rows of a node sampled for its parallel split's pivot
_SUBTREES_PER_THREAD = 4  # subtrees a thread builds whole (below the top levels), on average


class KdTree:
    """A k-d tree over ``(n, 3)`` float32 points (C-contiguous copies are made as needed).

    >>> tree = KdTree(np.array([[0, 0, 0], [1, 0, 0], [3, 0, 0]], np.float32))
    >>> indices, squared = tree.query(np.array([[0.9, 0, 0]], np.float32), k=2)
    >>> indices.tolist(), squared.round(2).tolist()
    ([[1, 0]], [[0.01, 0.81]])
    """

    def __init__(self, points: NDArray[np.floating], *, leaf_size: int = LEAF_SIZE) -> None:
        points = np.ascontiguousarray(points, dtype=np.float32)
        if points.ndim != 2 or points.shape[1] != 3:
            raise ShapeError(f"points: expected (n, 3), found {points.shape}")
        self.points = points
        n = points.shape[0]
        depth = 0
        while (n >> depth) > max(1, int(leaf_size)):
            depth += 1
        self.depth = depth
        # the points in tree order (a leaf's points contiguous) and their indices
        self._sorted, self.order, self.bounds, self.boxes, self.axes = _build(
            points, depth, numba.get_num_threads()
        )

    @property
    def n_points(self) -> int:
        """Number of points in the tree."""
        return int(self.points.shape[0])

    def query(
        self, queries: NDArray[np.floating], *, k: int
    ) -> tuple[NDArray[np.uint32], NDArray[np.float32]]:
        """``(indices, squared distances)``, each ``(m, k)``: the ``k`` nearest points of
        every query, nearest first (equal distances by index).

        Raises:
            ShapeError: ``queries`` is not ``(m, 3)``, or ``k`` is not in ``1..n_points``.
        """
        queries = np.ascontiguousarray(queries, dtype=np.float32)
        if queries.ndim != 2 or queries.shape[1] != 3:
            raise ShapeError(f"queries: expected (m, 3), found {queries.shape}")
        if not 1 <= k <= self.n_points:
            raise ShapeError(f"k: expected 1..{self.n_points}, found {k}")
        indices = np.empty((queries.shape[0], k), np.uint32)
        squared = np.empty((queries.shape[0], k), np.float32)
        _query(
            self._sorted,
            self.order,
            self.bounds,
            self.boxes,
            self.axes,
            self.depth,
            queries,
            indices,
            squared,
            numba.get_num_threads(),
        )
        return indices, squared


@numba.njit(cache=True, nogil=True, inline="always")
def _less(points: Any, order: Any, a: int, b: int, axis: int) -> bool:
    """Row ``a`` before row ``b`` along ``axis`` (ties by point index)."""
    pa, pb = points[a, axis], points[b, axis]
    return pa < pb or (pa == pb and order[a] < order[b])


@numba.njit(cache=True, nogil=True, inline="always")
def _swap(points: Any, order: Any, a: int, b: int) -> None:
    for axis in range(3):
        points[a, axis], points[b, axis] = points[b, axis], points[a, axis]
    order[a], order[b] = order[b], order[a]


@numba.njit(cache=True, nogil=True)
def _select(points: Any, order: Any, start: int, stop: int, nth: int, axis: int) -> None:
    """Reorder rows ``start:stop`` of ``points`` (and ``order`` with them) so that row
    ``nth`` holds the row it would hold sorted along ``axis`` (ties by point index), the
    rows before it not after it and the rows after it not before it."""
    low, high = start, stop - 1
    while low < high:
        middle = (low + high) // 2
        # median of three moved to ``middle``, then Hoare's partition around it
        if _less(points, order, middle, low, axis):
            _swap(points, order, middle, low)
        if _less(points, order, high, middle, axis):
            _swap(points, order, high, middle)
            if _less(points, order, middle, low, axis):
                _swap(points, order, middle, low)
        pivot_value = points[middle, axis]
        pivot_index = order[middle]
        i, j = low, high
        while i <= j:
            while points[i, axis] < pivot_value or (
                points[i, axis] == pivot_value and order[i] < pivot_index
            ):
                i += 1
            while pivot_value < points[j, axis] or (
                points[j, axis] == pivot_value and pivot_index < order[j]
            ):
                j -= 1
            if i <= j:
                _swap(points, order, i, j)
                i += 1
                j -= 1
        if nth <= j:
            high = j
        elif nth >= i:
            low = i
        else:
            return


@numba.njit(cache=True, nogil=True)
def _box(points: Any, start: int, stop: int, out: Any) -> None:
    for axis in range(3):
        out[axis] = np.inf
        out[3 + axis] = -np.inf
    for row in range(start, stop):
        for axis in range(3):
            value = np.float64(points[row, axis])
            out[axis] = min(out[axis], value)
            out[3 + axis] = max(out[3 + axis], value)


def _build(points: NDArray[np.float32], depth: int, n_threads: int) -> tuple[Any, ...]:
    """A tree in heap layout: node ``i`` has children ``2i+1``, ``2i+2``; leaves are the
    ``2**depth`` nodes of the last level. Returns the points in tree order, the point
    index of each of those rows, each node's rows (``bounds[i] = start, stop``) and each
    node's box (``lo xyz, hi xyz``) and split axis.

    A level with as many nodes as threads splits its nodes in parallel, each at its
    median row (a selection on one thread). A level with fewer (the top ones: the root
    alone would keep every other thread idle) splits its large nodes one after another,
    each on every thread: its box reduced in parallel, its rows partitioned in parallel
    about a pivot sampled from them and, when the pivot leaves less than a quarter on a
    side, at the median row as before. Children's boxes never overlap along the split
    axis, which is all a query needs: its result does not depend on where nodes are split.
    """
    n = points.shape[0]
    n_nodes = (1 << (depth + 1)) - 1
    ordered, order = _numbered_copy(points)
    bounds = np.zeros((n_nodes, 2), np.int64)
    boxes = np.zeros((n_nodes, 6), np.float64)
    axes = np.zeros(n_nodes, np.int64)
    bounds[0, 1] = n
    level = 0
    while level <= depth and (1 << level) < n_threads and n >> level >= _PARALLEL_SPLIT_ROWS:
        for node in range((1 << level) - 1, (1 << (level + 1)) - 1):
            start, stop = int(bounds[node, 0]), int(bounds[node, 1])
            _box_on_threads(ordered, start, stop, boxes[node])
            if level < depth:
                axes[node] = _split_on_threads(ordered, order, bounds, boxes[node], node, n_threads)
        level += 1
    _build_levels(ordered, order, bounds, boxes, axes, level, depth, n_threads)
    return ordered, order, bounds, boxes, axes


@numba.njit(cache=True, nogil=True, parallel=True)
def _numbered_copy(points: Any) -> tuple[Any, Any]:  # pragma: no cover - compiled
    """A copy of the points and their indices, written on every thread (numpy's copy and
    ``arange`` are passes on one thread before the first split)."""
    n = points.shape[0]
    ordered = np.empty((n, 3), points.dtype)
    order = np.empty(n, np.int64)
    for i in numba.prange(n):
        ordered[i, 0] = points[i, 0]
        ordered[i, 1] = points[i, 1]
        ordered[i, 2] = points[i, 2]
        order[i] = i
    return ordered, order


@numba.njit(cache=True, nogil=True, parallel=True)
def _build_levels(
    ordered: Any,
    order: Any,
    bounds: Any,
    boxes: Any,
    axes: Any,
    first_level: int,
    depth: int,
    n_threads: int,
) -> None:  # pragma: no cover - compiled
    """Levels ``first_level..depth`` of :func:`_build`, each node split at its median row
    on one thread: level by level (a level's nodes in parallel) while a level has fewer
    than ``_SUBTREES_PER_THREAD`` nodes a thread, then each node of that level's whole
    subtree on one thread, subtrees taken as threads come free (one wait for the lot
    instead of one a level, and a slow subtree does not hold a level's other threads)."""
    level = first_level
    while level <= depth and (1 << level) < _SUBTREES_PER_THREAD * n_threads:
        first = (1 << level) - 1
        for j in numba.prange(1 << level):
            _place_node(ordered, order, bounds, boxes, axes, first + j, level < depth)
        level += 1
    if level > depth:
        return
    first = (1 << level) - 1
    count = 1 << level
    taken = np.zeros(1, np.int64)
    for _ in numba.prange(row_workers(n_threads, count, 1)):
        while True:
            start, stop = take_row_block(taken, count, 1)
            if start >= stop:
                break
            root = first + start
            for below in range(depth - level + 1):  # the subtree level by level
                first_below = ((root + 1) << below) - 1
                for j in range(1 << below):
                    _place_node(
                        ordered, order, bounds, boxes, axes, first_below + j, level + below < depth
                    )


@numba.njit(cache=True, nogil=True, inline="always")
def _place_node(
    ordered: Any, order: Any, bounds: Any, boxes: Any, axes: Any, node: int, split: bool
) -> None:  # pragma: no cover - compiled
    """Node ``node``'s box and, when ``split``, its split at its median row."""
    box = boxes[node]
    _box(ordered, bounds[node, 0], bounds[node, 1], box)
    if split:
        axes[node] = _split(ordered, order, bounds, box, node)


@numba.njit(cache=True, nogil=True, parallel=True)
def _box_on_threads(points: Any, start: int, stop: int, out: Any) -> None:  # pragma: no cover
    """:func:`_box` of rows ``start:stop``, reduced on every thread."""
    x_low = y_low = z_low = np.inf
    x_high = y_high = z_high = -np.inf
    for row in numba.prange(start, stop):
        x = np.float64(points[row, 0])
        y = np.float64(points[row, 1])
        z = np.float64(points[row, 2])
        x_low = min(x_low, x)
        y_low = min(y_low, y)
        z_low = min(z_low, z)
        x_high = max(x_high, x)
        y_high = max(y_high, y)
        z_high = max(z_high, z)
    out[0], out[1], out[2] = x_low, y_low, z_low
    out[3], out[4], out[5] = x_high, y_high, z_high


@numba.njit(cache=True, nogil=True, parallel=True)
def _split_on_threads(
    points: Any, order: Any, bounds: Any, box: Any, node: int, n_threads: int
) -> int:  # pragma: no cover - compiled
    """Split a node along its box's widest axis on every thread: rows below a pivot
    sampled from the node's rows first (stable partition: counts per block, then each
    block's rows to their places); at the median row (:func:`_split`) when the pivot
    leaves less than a quarter on a side. Returns the axis."""
    start, stop = bounds[node, 0], bounds[node, 1]
    axis = _widest_axis(box)
    size = stop - start
    step = max(1, size // _PIVOT_SAMPLE)
    sample = np.sort(points[start:stop:step, axis])
    pivot = sample[sample.shape[0] // 2]
    n_blocks = max(1, min(4 * n_threads, size // 8192))
    block = (size + n_blocks - 1) // n_blocks
    below = np.zeros(n_blocks, np.int64)
    for b in numba.prange(n_blocks):
        count = 0
        for row in range(start + b * block, min(stop, start + (b + 1) * block)):
            if points[row, axis] < pivot:
                count += 1
        below[b] = count
    n_below = below.sum()
    if n_below < size // 4 or n_below > size - size // 4:
        return _split(points, order, bounds, box, node)
    low_at = np.empty(n_blocks, np.int64)
    high_at = np.empty(n_blocks, np.int64)
    low, high = 0, n_below
    for b in range(n_blocks):
        low_at[b] = low
        high_at[b] = high
        rows = max(0, min(stop, start + (b + 1) * block) - (start + b * block))
        low += below[b]
        high += rows - below[b]
    moved = np.empty((size, 3), points.dtype)
    moved_order = np.empty(size, np.int64)
    for b in numba.prange(n_blocks):
        low, high = low_at[b], high_at[b]
        for row in range(start + b * block, min(stop, start + (b + 1) * block)):
            if points[row, axis] < pivot:
                place = low
                low += 1
            else:
                place = high
                high += 1
            moved[place, 0] = points[row, 0]
            moved[place, 1] = points[row, 1]
            moved[place, 2] = points[row, 2]
            moved_order[place] = order[row]
    for i in numba.prange(size):
        points[start + i, 0] = moved[i, 0]
        points[start + i, 1] = moved[i, 1]
        points[start + i, 2] = moved[i, 2]
        order[start + i] = moved_order[i]
    middle = start + n_below
    _set_children(bounds, node, start, middle, stop)
    return axis


@numba.njit(cache=True, nogil=True)
def _split(points: Any, order: Any, bounds: Any, box: Any, node: int) -> int:
    """Split a node at its middle row along its box's widest axis; return the axis."""
    start, stop = bounds[node, 0], bounds[node, 1]
    axis = _widest_axis(box)
    middle = start + (stop - start) // 2
    if stop - start > 1:
        _select(points, order, start, stop, middle, axis)
    _set_children(bounds, node, start, middle, stop)
    return axis


@numba.njit(cache=True, nogil=True, inline="always")
def _widest_axis(box: Any) -> int:  # pragma: no cover - compiled
    """The axis along which ``box`` (``lo xyz, hi xyz``) is widest (the first of equals)."""
    axis = 0
    for candidate in range(1, 3):
        if box[3 + candidate] - box[candidate] > box[3 + axis] - box[axis]:
            axis = candidate
    return axis


@numba.njit(cache=True, nogil=True, inline="always")
def _set_children(
    bounds: Any, node: int, start: int, middle: int, stop: int
) -> None:  # pragma: no cover
    """Node ``node``'s children hold its rows ``start:middle`` and ``middle:stop``."""
    bounds[2 * node + 1, 0] = start
    bounds[2 * node + 1, 1] = middle
    bounds[2 * node + 2, 0] = middle
    bounds[2 * node + 2, 1] = stop


@numba.njit(cache=True, nogil=True, inline="always")
def _worse(d1: Any, i1: Any, d2: Any, i2: Any) -> bool:
    """``(d1, i1) > (d2, i2)``."""
    return d1 > d2 or (d1 == d2 and i1 > i2)


@numba.njit(cache=True, nogil=True)
def _search(
    points: Any,
    order: Any,
    bounds: Any,
    boxes: Any,
    axes: Any,
    depth: int,
    query: Any,
    k: int,
    best_d: Any,
    best_i: Any,
    stack: Any,
    stack_d: Any,
) -> None:  # pragma: no cover - compiled
    """The k smallest (distance, index) pairs of one query, ascending, into ``best_*``
    (``points`` in tree order: ``points[i]`` is point ``order[i]``).

    Depth first, nearer child first; a node is skipped when a lower bound of its distance
    (kept per axis as the search descends, as nanoflann does) exceeds the k-th distance
    found. ``stack_d`` rows hold that bound and its three per-axis parts.
    """
    qx, qy, qz = query[0], query[1], query[2]
    size = 0
    first_leaf = (1 << depth) - 1
    stack[0] = 0
    total = 0.0
    for axis in range(3):
        value = np.float64(query[axis])
        low, high = boxes[0, axis], boxes[0, 3 + axis]
        gap = low - value if value < low else (value - high if value > high else 0.0)
        stack_d[0, 1 + axis] = gap * gap
        total += gap * gap
    stack_d[0, 0] = total
    top = 1
    while top:
        top -= 1
        node = stack[top]
        bound = stack_d[top, 0]
        if size == k and bound > np.float64(best_d[k - 1]) * (1.0 + _PRUNE_MARGIN) + 1e-30:
            continue
        if node >= first_leaf:
            for position in range(bounds[node, 0], bounds[node, 1]):
                dx = qx - points[position, 0]
                dy = qy - points[position, 1]
                dz = qz - points[position, 2]
                d = (dx * dx + dy * dy) + dz * dz
                if size == k:
                    if d > best_d[k - 1]:
                        continue
                    p = order[position]
                    if not _worse(best_d[k - 1], best_i[k - 1], d, p):
                        continue
                    c = k - 1
                else:
                    p = order[position]
                    c = size
                    size += 1
                while c > 0 and _worse(best_d[c - 1], best_i[c - 1], d, p):
                    best_d[c] = best_d[c - 1]
                    best_i[c] = best_i[c - 1]
                    c -= 1
                best_d[c] = d
                best_i[c] = p
            continue
        axis = axes[node]
        left, right = 2 * node + 1, 2 * node + 2
        value = np.float64(query[axis])
        below = value - boxes[left, 3 + axis]  # past the left child's highest
        above = value - boxes[right, axis]  # past the right child's lowest
        if below + above < 0.0:  # nearer the left child
            near, far, cut = left, right, above * above
        else:
            near, far, cut = right, left, below * below
        # the far child: the bound with this axis's part replaced by the cut's
        stack[top] = far
        stack_d[top, 0] = bound - stack_d[top, 1 + axis] + cut
        stack_d[top + 1, 0] = bound
        for part in range(3):
            stack_d[top + 1, 1 + part] = stack_d[top, 1 + part]
        stack_d[top, 1 + axis] = cut
        stack[top + 1] = near
        top += 2


@numba.njit(cache=True, nogil=True, parallel=True)
def _query(
    points: Any,
    order: Any,
    bounds: Any,
    boxes: Any,
    axes: Any,
    depth: int,
    queries: Any,
    indices: Any,
    squared: Any,
    n_threads: int,
) -> None:  # pragma: no cover - compiled
    m, k = indices.shape
    taken = np.zeros(1, np.int64)
    # blocks taken as threads come free: a search costs more where points crowd or tie
    for _ in numba.prange(row_workers(n_threads, m, _QUERY_BLOCK)):
        best_d = np.empty(k, np.float32)
        best_i = np.empty(k, np.int64)
        stack = np.empty(depth + 2, np.int64)
        stack_d = np.empty((depth + 2, 4), np.float64)
        while True:
            start, stop = take_row_block(taken, m, _QUERY_BLOCK)
            if start >= stop:
                break
            for row in range(start, stop):
                _search(
                    points,
                    order,
                    bounds,
                    boxes,
                    axes,
                    depth,
                    queries[row],
                    k,
                    best_d,
                    best_i,
                    stack,
                    stack_d,
                )
                for a in range(k):
                    indices[row, a] = best_i[a]
                    squared[row, a] = best_d[a]
