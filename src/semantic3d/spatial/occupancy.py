"""``OccupancyGrid``: which voxels of a tile hold points, to skip hopeless neighbour queries.

The label-agreement check asks, for every point of one scan, for its nearest neighbour in
the other scan within a few centimetres. Two stations' scans overlap only in part, and
far from a scanner its points are centimetres to decimetres apart, so most queries find
nothing. A voxel grid whose cells are at least as large as the matching distance answers
"can this point have a neighbour at all?" exactly: a neighbour within the distance lies in
the point's own voxel or one of the 26 around it. Points that fail the test are neither
queried nor put in the k-d tree. The voxel keys also give a spatially coherent order
(row-major voxels) in which k-d tree builds and queries run several times faster than in
file order.
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import NDArray

MAX_CELLS = 1 << 24
"""Largest grid (16 Mi one-byte cells); the cell doubles past it."""

CELLS_PER_POINT = 8
"""Grids are also kept below this many cells per point: a grid much larger than its
points costs more in zeroed pages than the queries it saves."""


@numba.njit(cache=True, nogil=True)
def _touching(
    marks: NDArray[np.bool_], keys: NDArray[np.int64], offsets: NDArray[np.int64]
) -> NDArray[np.bool_]:  # pragma: no cover - compiled
    # Hand-written: 27 numpy gathers per point cost ~30x more than this loop, which stops
    # at the first marked neighbour (usually the point's own voxel, offsets[0] == 0).
    out = np.zeros(keys.shape[0], dtype=np.bool_)
    for i in range(keys.shape[0]):
        key = keys[i]
        for offset in offsets:
            if marks[key + offset]:
                out[i] = True
                break
    return out


class OccupancyGrid:
    """A dense voxel grid over a set of points, with one cell of padding on every side.

    Args:
        parts: ``(n, >=3)`` arrays whose first three columns are x y z; the grid covers all.
        cell_m: the smallest cell side; :meth:`touching` is an exact filter for neighbours
            within ``cell_m``. Doubled while the grid would exceed ``max_cells`` or
            :data:`CELLS_PER_POINT` cells per point.
    """

    def __init__(
        self, parts: list[NDArray[np.float64]], *, cell_m: float, max_cells: int = MAX_CELLS
    ) -> None:
        if not cell_m > 0:
            raise ValueError(f"cell_m: expected a positive size, found {cell_m}")
        filled = [p for p in parts if p.shape[0]]
        n_points = sum(p.shape[0] for p in filled)
        max_cells = min(max_cells, max(CELLS_PER_POINT * n_points, 1 << 12))
        low, high = np.zeros(3), np.zeros(3)
        for axis in range(3):
            if filled:
                low[axis] = min(float(p[:, axis].min()) for p in filled)
                high[axis] = max(float(p[:, axis].max()) for p in filled)
        while True:
            origin = low - cell_m  # one padding cell below...
            dims = np.floor((high - origin) / cell_m).astype(np.int64) + 2  # ...and above
            if int(np.prod(dims)) <= max_cells:
                break
            cell_m *= 2
        self.cell_m = cell_m
        self.origin = origin
        self.shape: tuple[int, int, int] = (int(dims[0]), int(dims[1]), int(dims[2]))
        strides = (self.shape[1] * self.shape[2], self.shape[2], 1)
        offsets = sorted(
            (dx * strides[0] + dy * strides[1] + dz * strides[2])
            for dx in (-1, 0, 1)
            for dy in (-1, 0, 1)
            for dz in (-1, 0, 1)
        )
        offsets.remove(0)
        self._offsets = np.array([0, *offsets], dtype=np.int64)

    @property
    def n_cells(self) -> int:
        """Number of voxels, padding included."""
        return self.shape[0] * self.shape[1] * self.shape[2]

    def keys(self, points: NDArray[np.float64]) -> NDArray[np.int64]:
        """Row-major voxel index of each point (points must lie inside the covered box)."""
        keys = np.zeros(points.shape[0], dtype=np.int64)
        for axis in range(3):
            index = np.floor((points[:, axis] - self.origin[axis]) / self.cell_m)
            if axis:
                keys *= self.shape[axis]
            keys += index.astype(np.int64)
        return keys

    def mark(self, *keys: NDArray[np.int64]) -> NDArray[np.bool_]:
        """Flat mask of the voxels holding at least one of ``keys``."""
        marks = np.zeros(self.n_cells, dtype=bool)
        for part in keys:
            marks[part] = True
        return marks

    def touching(self, marks: NDArray[np.bool_], keys: NDArray[np.int64]) -> NDArray[np.bool_]:
        """For each key, whether its voxel or one of the 26 around it is marked."""
        return _touching(marks, np.ascontiguousarray(keys, dtype=np.int64), self._offsets)
