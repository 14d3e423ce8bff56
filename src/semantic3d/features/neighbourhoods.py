"""k nearest neighbours in one pyramid level, in a canonical order.

A constant, small ``k`` per level (Hackel et al. 2016: k = 10) replaces a radius search:
the pyramid already sets the scale, and a fixed k keeps the cost per query constant
however dense the scan. The search is the package's k-d tree
(:class:`~semantic3d.spatial.kdtree.KdTree`: float32 coordinates relative to the grid
origin, nanoflann's distance arithmetic, built and searched on the thread budget's cores
without the GIL, so tiles of a scan search at the same time). Features are then computed
from the float64 points.

Canonical order: neighbours are sorted by distance, ties broken by voxel key. The k-d
tree is asked for one neighbour more than needed; when the k-th and the last returned
distances are equal, the tie may continue past the returned ones and those rows are asked
again with more neighbours. The result is therefore a function of the point set alone,
not of the tree's layout: a tile plus a wide enough halo yields exactly the neighbours
(and sums in exactly the order) of the whole scan.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np
from numpy.typing import NDArray

from semantic3d.core.errors import ShapeError
from semantic3d.features._row_kernels import leading_columns
from semantic3d.spatial.kdtree import KdTree


@dataclass(frozen=True, slots=True)
class Neighbours:
    """k-NN result for a batch of queries.

    Attributes:
        indices: ``(m, k_eff)`` uint32 indices into the searched points, canonical order;
            ``k_eff = min(k, n_points)`` (may be a strided view).
        kth_distance: ``(m,)`` float64 distance of the farthest selected neighbour (from the
            float32 search; exact to ~1e-7 of the distance to the grid origin).
    """

    indices: NDArray[np.uint32]
    kth_distance: NDArray[np.float64]


class LevelIndex:
    """A k-d tree over one pyramid level's points, with their keys for tie-breaking.

    Args:
        xyz: ``(n, 3)`` float64 points (relative to the grid origin).
        keys: ``(n,)`` int64 unique voxel keys of the points.
    """

    def __init__(self, xyz: NDArray[np.float64], keys: NDArray[np.int64]) -> None:
        if xyz.ndim != 2 or xyz.shape[1] != 3 or keys.shape != (xyz.shape[0],):
            raise ShapeError(
                f"xyz/keys: expected (n, 3) and (n,), found {xyz.shape} and {keys.shape}"
            )
        self.xyz = np.ascontiguousarray(xyz, dtype=np.float64)
        self.keys = np.ascontiguousarray(keys, dtype=np.int64)
        self._xyz32 = self.xyz.astype(np.float32)
        self._tree: KdTree | None = None

    @property
    def n_points(self) -> int:
        """Number of indexed points."""
        return int(self.xyz.shape[0])

    def query(self, queries: NDArray[np.float64], *, k: int) -> Neighbours:
        """The ``min(k, n_points)`` nearest indexed points of every query, canonical order."""
        queries = np.ascontiguousarray(queries, dtype=np.float64)
        if queries.ndim != 2 or queries.shape[1] != 3:
            raise ShapeError(f"queries: expected (m, 3), found {queries.shape}")
        if self.n_points == 0:
            raise ShapeError("k-NN query on an empty point set")
        k_eff = min(k, self.n_points)
        # the level's own points as queries (voxel mode): reuse their float32 copy
        queries32 = self._xyz32 if queries is self.xyz else queries.astype(np.float32)
        k_query = min(k_eff + 1, self.n_points)
        if self._tree is None:
            self._tree = KdTree(self._xyz32)
        found, squared = self._tree.query(queries32, k=k_query)
        pending = np.flatnonzero(
            _canonicalise(squared, found, self.keys, k_eff, k_query < self.n_points)
        )
        indices = found if k_query == k_eff else leading_columns(found, k_eff)
        kth = np.sqrt(squared[:, k_eff - 1].astype(np.float64))
        if pending.size:  # ties reaching past the returned neighbours: ask for more
            self._resolve_ties(
                queries32[pending],
                pending,
                squared[pending, k_eff - 1],
                k_eff,
                k_query,
                indices,
                kth,
            )
        return Neighbours(indices=indices, kth_distance=kth)

    def _resolve_ties(
        self,
        queries32: NDArray[np.float32],
        rows: NDArray[np.intp],
        squared_kth: NDArray[np.float32],
        k_eff: int,
        k_query: int,
        indices: NDArray[np.uint32],
        kth: NDArray[np.float64],
    ) -> None:
        """Canonical neighbours of ``rows`` whose tie at the k-th distance was cut off.

        Asked again with twice the neighbours, among only the indexed points inside a box
        holding each row's ball of its k-th distance: a complete superset of the points
        that can be selected, with the same float32 coordinates (so the same distances),
        and a k-d tree over a few hundred points instead of the whole level.
        """
        # float32 distances carry ~1e-7 relative error: the 1e-4 margin keeps the box a
        # superset of the ball; a zero k-th distance keeps a positive half-width
        radii = np.sqrt(squared_kth.astype(np.float64)) * (1.0 + 1e-4) + 1e-30
        subset = np.flatnonzero(_points_in_boxes(self._xyz32, queries32, radii))
        tree = KdTree(self._xyz32[subset])
        keys = self.keys[subset]
        while rows.size:
            k_query = min(2 * k_query, subset.size)
            more, more_squared = tree.query(queries32, k=k_query)
            ambiguous = _canonicalise(more_squared, more, keys, k_eff, k_query < subset.size)
            done = ~ambiguous
            indices[rows[done]] = subset[more[done, :k_eff]]
            kth[rows[done]] = np.sqrt(more_squared[done, k_eff - 1].astype(np.float64))
            rows = rows[ambiguous]
            queries32 = queries32[ambiguous]


# Hand-written: marks the points inside any of a few hundred small boxes without testing
# every point against every box (or building a tree): boxes are hashed to the cells of a
# grid at least as coarse as the widest box (so a box meets at most 2 cells per axis) and
# each point tests only the boxes of its own cell.
@numba.njit(cache=True, nogil=True, parallel=True)
def _points_in_boxes(
    points: NDArray[np.float32], centres: NDArray[np.float32], radii: NDArray[np.float64]
) -> NDArray[np.bool_]:  # pragma: no cover - compiled
    """``mask[p]``: point p lies in the cube of half-width ``radii[i]`` about some centre i."""
    n_boxes = centres.shape[0]
    low = np.full(3, np.inf)
    high = np.full(3, -np.inf)
    for i in range(n_boxes):
        for axis in range(3):
            low[axis] = min(low[axis], np.float64(centres[i, axis]) - radii[i])
            high[axis] = max(high[axis], np.float64(centres[i, axis]) + radii[i])
    extent = max(high[0] - low[0], max(high[1] - low[1], high[2] - low[2]))
    cell = max(2.0 * radii.max(), extent / 2.0**20)
    codes = np.empty(27 * n_boxes, np.int64)
    owner = np.empty(27 * n_boxes, np.int64)
    count = 0
    for i in range(n_boxes):
        first = np.empty(3, np.int64)
        last = np.empty(3, np.int64)
        for axis in range(3):
            centre = np.float64(centres[i, axis])
            first[axis] = math.floor((centre - radii[i] - low[axis]) / cell)
            last[axis] = math.floor((centre + radii[i] - low[axis]) / cell)
        for cx in range(first[0], last[0] + 1):
            for cy in range(first[1], last[1] + 1):
                for cz in range(first[2], last[2] + 1):
                    codes[count] = (cx << 42) | (cy << 21) | cz
                    owner[count] = i
                    count += 1
    order = np.argsort(codes[:count])
    codes = codes[order]
    owner = owner[order]
    mask = np.zeros(points.shape[0], np.bool_)
    for p in numba.prange(points.shape[0]):
        x = np.float64(points[p, 0])
        y = np.float64(points[p, 1])
        z = np.float64(points[p, 2])
        if x < low[0] or x > high[0] or y < low[1] or y > high[1] or z < low[2] or z > high[2]:
            continue
        code = (
            (math.floor((x - low[0]) / cell) << 42)
            | (math.floor((y - low[1]) / cell) << 21)
            | math.floor((z - low[2]) / cell)
        )
        j = np.searchsorted(codes, code)
        while j < count and codes[j] == code:
            i = owner[j]
            if (
                abs(x - np.float64(centres[i, 0])) <= radii[i]
                and abs(y - np.float64(centres[i, 1])) <= radii[i]
                and abs(z - np.float64(centres[i, 2])) <= radii[i]
            ):
                mask[p] = True
                break
            j += 1
    return mask


# Hand-written: reorders ties inside each row (a few compares per query) without
# building an (m, k) lexsort; runs on every query of every level.
@numba.njit(cache=True, nogil=True, parallel=True)
def _canonicalise(
    distances: NDArray[np.float32],
    found: NDArray[np.uint32],
    keys: NDArray[np.int64],
    k_eff: int,
    truncated: bool,
) -> NDArray[np.bool_]:  # pragma: no cover - compiled
    """Sort each row's runs of equal distance by key (in place); flag unresolvable rows."""
    m, width = found.shape
    ambiguous = np.zeros(m, np.bool_)
    for row in numba.prange(m):
        if truncated and distances[row, width - 1] == distances[row, k_eff - 1]:
            ambiguous[row] = True
            continue
        start = 0
        while start < width:
            end = start + 1
            while end < width and distances[row, end] == distances[row, start]:
                end += 1
            if end - start > 1:
                for i in range(start + 1, end):  # insertion sort of the tie run by key
                    item = found[row, i]
                    j = i - 1
                    while j >= start and keys[found[row, j]] > keys[item]:
                        found[row, j + 1] = found[row, j]
                        j -= 1
                    found[row, j + 1] = item
            if end >= k_eff:
                break
            start = end
    return ambiguous


# Hand-written: the k-th nearest distance of a handful of queries among up to millions of
# points, without building a k-d tree over them (a tree costs far more than the scan).
@numba.njit(cache=True, nogil=True, parallel=True)
def kth_squared_distances(
    points: NDArray[np.float64], queries: NDArray[np.float64], k: int
) -> NDArray[np.float64]:  # pragma: no cover - compiled
    """The ``k``-th smallest squared distance from each query to ``points`` (``n >= k``),
    by a scan of every point: for a few queries (cost ``m * n``)."""
    m = queries.shape[0]
    out = np.empty(m, np.float64)
    for row in numba.prange(m):
        best = np.full(k, np.inf)  # ascending: the k smallest so far
        qx = queries[row, 0]
        qy = queries[row, 1]
        qz = queries[row, 2]
        for p in range(points.shape[0]):
            dx = points[p, 0] - qx
            dy = points[p, 1] - qy
            dz = points[p, 2] - qz
            d = dx * dx + dy * dy + dz * dz
            if d < best[k - 1]:
                j = k - 1
                while j > 0 and best[j - 1] > d:
                    best[j] = best[j - 1]
                    j -= 1
                best[j] = d
        out[row] = best[k - 1]
    return out
