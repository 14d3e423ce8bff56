"""Exact k nearest neighbours of float32 points: a k-d tree built and searched on all cores.

Hand-written (numba) because the library it replaces here, pgeof's nanoflann search,
holds the GIL for the whole call, builds its tree on one thread and starts one thread
per core of the machine on every call whatever the process was asked to use: tiles of a
scan could not be searched at the same time and ``--threads`` could not cap it. This tree
is built level by level (the nodes of a level split in parallel), searched in parallel
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

from semantic3d.core.errors import ShapeError

__all__ = ["KdTree"]

LEAF_SIZE = 16
_QUERY_BLOCK = 256  # queries per parallel task (one heap and stack each)
_PRUNE_MARGIN = 1e-5  # relative: a node's float64 box distance vs float32 point distances


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
        self.order, self.bounds, self.boxes = _build(points, depth)
        # the points in tree order: a leaf's points are contiguous in memory
        self._sorted = np.ascontiguousarray(points[self.order])

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
            self._sorted, self.order, self.bounds, self.boxes, self.depth, queries, indices, squared
        )
        return indices, squared


@numba.njit(cache=True, nogil=True)
def _select(points: Any, order: Any, start: int, stop: int, nth: int, axis: int) -> None:
    """Reorder ``order[start:stop]`` so that position ``nth`` holds the point it would hold
    sorted by coordinate ``axis`` (ties by index), smaller before, larger after."""
    low, high = start, stop - 1
    while low < high:
        middle = (low + high) // 2
        # median of three as the pivot, compared as (coordinate, index)
        a, b, c = order[low], order[middle], order[high]
        if _less(points, b, a, axis):
            a, b = b, a
        if _less(points, c, b, axis):
            b, c = c, b
            if _less(points, b, a, axis):
                a, b = b, a
        pivot = b
        i, j = low, high
        while i <= j:
            while _less(points, order[i], pivot, axis):
                i += 1
            while _less(points, pivot, order[j], axis):
                j -= 1
            if i <= j:
                order[i], order[j] = order[j], order[i]
                i += 1
                j -= 1
        if nth <= j:
            high = j
        elif nth >= i:
            low = i
        else:
            return


@numba.njit(cache=True, nogil=True, inline="always")
def _less(points: Any, a: Any, b: Any, axis: int) -> bool:
    pa, pb = points[a, axis], points[b, axis]
    return pa < pb or (pa == pb and a < b)


@numba.njit(cache=True, nogil=True)
def _box(points: Any, order: Any, start: int, stop: int, out: Any) -> None:
    for axis in range(3):
        out[axis] = np.inf
        out[3 + axis] = -np.inf
    for position in range(start, stop):
        p = order[position]
        for axis in range(3):
            value = points[p, axis]
            out[axis] = min(out[axis], value)
            out[3 + axis] = max(out[3 + axis], value)


@numba.njit(cache=True, nogil=True, parallel=True)
def _build(points: Any, depth: int) -> tuple[Any, Any, Any]:  # pragma: no cover - compiled
    """A balanced tree in heap layout: node ``i`` has children ``2i+1``, ``2i+2``; leaves
    are the ``2**depth`` nodes of the last level. Returns the point order (each node's
    points are ``order[bounds[i, 0]:bounds[i, 1]]``), the bounds and each node's box
    (``lo xyz, hi xyz``)."""
    n = points.shape[0]
    n_nodes = (1 << (depth + 1)) - 1
    order = np.arange(n).astype(np.int64)
    bounds = np.zeros((n_nodes, 2), np.int64)
    boxes = np.zeros((n_nodes, 6), np.float64)
    bounds[0, 1] = n
    for level in range(depth + 1):
        first = (1 << level) - 1
        count = 1 << level
        for j in numba.prange(count):
            node = first + j
            start, stop = bounds[node, 0], bounds[node, 1]
            box = np.empty(6, np.float64)
            _box(points, order, start, stop, box)
            boxes[node] = box
            if level < depth:
                _split(points, order, bounds, box, node)
    return order, bounds, boxes


@numba.njit(cache=True, nogil=True)
def _split(points: Any, order: Any, bounds: Any, box: Any, node: int) -> None:
    """Split a node at its middle point along its box's widest axis."""
    start, stop = bounds[node, 0], bounds[node, 1]
    axis = 0
    for candidate in range(1, 3):
        if box[3 + candidate] - box[candidate] > box[3 + axis] - box[axis]:
            axis = candidate
    middle = start + (stop - start) // 2
    if stop - start > 1:
        _select(points, order, start, stop, middle, axis)
    bounds[2 * node + 1, 0] = start
    bounds[2 * node + 1, 1] = middle
    bounds[2 * node + 2, 0] = middle
    bounds[2 * node + 2, 1] = stop


@numba.njit(cache=True, nogil=True, inline="always")
def _box_distance(boxes: Any, node: int, x: float, y: float, z: float) -> float:
    return _gap(boxes[node, 0], boxes[node, 3], x) + (
        _gap(boxes[node, 1], boxes[node, 4], y) + _gap(boxes[node, 2], boxes[node, 5], z)
    )


@numba.njit(cache=True, nogil=True, inline="always")
def _gap(low: float, high: float, value: float) -> float:
    gap = low - value if value < low else (value - high if value > high else 0.0)
    return gap * gap


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
    depth: int,
    query: Any,
    k: int,
    heap_d: Any,
    heap_i: Any,
    stack: Any,
    stack_d: Any,
) -> None:  # pragma: no cover - compiled
    """The k smallest (distance, index) pairs of one query into a max-heap of size k
    (``points`` in tree order: ``points[i]`` is point ``order[i]``)."""
    qx, qy, qz = query[0], query[1], query[2]
    x, y, z = np.float64(qx), np.float64(qy), np.float64(qz)
    size = 0
    first_leaf = (1 << depth) - 1
    top = 0
    stack[0] = 0
    stack_d[0] = 0.0
    top = 1
    while top:
        top -= 1
        node = stack[top]
        if size == k and stack_d[top] > np.float64(heap_d[0]) * (1.0 + _PRUNE_MARGIN) + 1e-30:
            continue
        if node >= first_leaf:
            for position in range(bounds[node, 0], bounds[node, 1]):
                p = order[position]
                dx = qx - points[position, 0]
                dy = qy - points[position, 1]
                dz = qz - points[position, 2]
                d = (dx * dx + dy * dy) + dz * dz
                if size < k:
                    # sift up
                    c = size
                    size += 1
                    while c > 0:
                        parent = (c - 1) // 2
                        if _worse(d, p, heap_d[parent], heap_i[parent]):
                            heap_d[c] = heap_d[parent]
                            heap_i[c] = heap_i[parent]
                            c = parent
                        else:
                            break
                    heap_d[c] = d
                    heap_i[c] = p
                elif _worse(heap_d[0], heap_i[0], d, p):
                    # replace the root, sift down
                    c = 0
                    while True:
                        child = 2 * c + 1
                        if child >= k:
                            break
                        if child + 1 < k and _worse(
                            heap_d[child + 1], heap_i[child + 1], heap_d[child], heap_i[child]
                        ):
                            child += 1
                        if _worse(heap_d[child], heap_i[child], d, p):
                            heap_d[c] = heap_d[child]
                            heap_i[c] = heap_i[child]
                            c = child
                        else:
                            break
                    heap_d[c] = d
                    heap_i[c] = p
            continue
        left, right = 2 * node + 1, 2 * node + 2
        dl = _box_distance(boxes, left, x, y, z)
        dr = _box_distance(boxes, right, x, y, z)
        if dl <= dr:  # the nearer child is popped first
            stack[top], stack_d[top] = right, dr
            stack[top + 1], stack_d[top + 1] = left, dl
        else:
            stack[top], stack_d[top] = left, dl
            stack[top + 1], stack_d[top + 1] = right, dr
        top += 2


@numba.njit(cache=True, nogil=True, parallel=True)
def _query(
    points: Any,
    order: Any,
    bounds: Any,
    boxes: Any,
    depth: int,
    queries: Any,
    indices: Any,
    squared: Any,
) -> None:  # pragma: no cover - compiled
    m, k = indices.shape
    n_blocks = (m + _QUERY_BLOCK - 1) // _QUERY_BLOCK
    for block in numba.prange(n_blocks):
        heap_d = np.empty(k, np.float32)
        heap_i = np.empty(k, np.int64)
        stack = np.empty(2 * depth + 2, np.int64)
        stack_d = np.empty(2 * depth + 2, np.float64)
        for row in range(block * _QUERY_BLOCK, min(m, (block + 1) * _QUERY_BLOCK)):
            _search(
                points, order, bounds, boxes, depth, queries[row], k, heap_d, heap_i, stack, stack_d
            )
            # heap -> ascending (k is small: insertion sort)
            for a in range(1, k):
                d, i = heap_d[a], heap_i[a]
                b = a - 1
                while b >= 0 and _worse(heap_d[b], heap_i[b], d, i):
                    heap_d[b + 1] = heap_d[b]
                    heap_i[b + 1] = heap_i[b]
                    b -= 1
                heap_d[b + 1] = d
                heap_i[b + 1] = i
            for a in range(k):
                indices[row, a] = heap_i[a]
                squared[row, a] = heap_d[a]
