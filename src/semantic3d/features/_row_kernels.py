"""Compiled copies, gathers and look-ups over the rows of feature tables and k-NN lists.

Hand-written: numpy's fancy indexing, ``searchsorted`` and strided copies run on one
thread, and a fresh table's pages are then first touched on that thread too. Inside the
densest tile of a scan (near the scanner, often more than half its points) these steps
ran alone between the parallel kernels. Each kernel here writes what the numpy
expression it replaces would, row by row on numba's threads.
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import NDArray

from semantic3d.spatial.voxels import CELL_BITS  # packed keys: x, y, z of this many bits each

__all__ = [
    "copy_rows",
    "distinct_values",
    "exact_rows",
    "leading_columns",
    "put_rows",
    "put_values",
    "rows_in_box",
    "rows_of_keys",
    "scatter_rows",
    "store_keys",
    "take_rows",
]


@numba.njit(cache=True, nogil=True, parallel=True)
def copy_rows(block: NDArray[np.generic], out: NDArray[np.generic]) -> None:  # pragma: no cover
    """``out[...] = block`` for two ``(m, w)`` arrays (``out`` may be a column slice)."""
    for row in numba.prange(block.shape[0]):
        for column in range(block.shape[1]):
            out[row, column] = block[row, column]


def take_rows(source: NDArray[np.float64], rows: NDArray[np.intp]) -> NDArray[np.float64]:
    """``source[rows]`` for a 2-D ``source`` (gathered by :func:`put_rows`)."""
    out = np.empty((rows.size, source.shape[1]), source.dtype)
    put_rows(source, rows, out, 0)
    return out


@numba.njit(cache=True, nogil=True, parallel=True)
def scatter_rows(
    source: NDArray[np.generic], rows: NDArray[np.intp], out: NDArray[np.generic]
) -> None:  # pragma: no cover - compiled
    """``out[rows] = source`` for 2-D arrays (``out`` may be a column slice; ``rows``
    distinct)."""
    for i in numba.prange(rows.size):
        for column in range(source.shape[1]):
            out[rows[i], column] = source[i, column]


def leading_columns(found: NDArray[np.uint32], width: int) -> NDArray[np.uint32]:
    """``np.ascontiguousarray(found[:, :width])`` (copied by :func:`copy_rows`)."""
    out = np.empty((found.shape[0], width), found.dtype)
    copy_rows(found[:, :width], out)
    return out


@numba.njit(cache=True, nogil=True, parallel=True)
def store_keys(
    keys: NDArray[np.int64],
    found: NDArray[np.int64],
    exact: NDArray[np.bool_],
    out: NDArray[np.int64],
) -> None:  # pragma: no cover - compiled
    """For every row with ``exact``: ``out[row, :w] = keys[found[row]]`` (``w`` found's
    width) and ``-1`` in the columns past ``w``."""
    width = found.shape[1]
    for row in numba.prange(found.shape[0]):
        if not exact[row]:
            continue
        for column in range(width):
            out[row, column] = keys[found[row, column]]
        for column in range(width, out.shape[1]):
            out[row, column] = -1


@numba.njit(cache=True, nogil=True, parallel=True)
def exact_rows(
    queries: NDArray[np.float64],
    reach: NDArray[np.float64],
    box: NDArray[np.float64],
    infinite: NDArray[np.bool_],
    enough: bool,
    margin_m: float,
) -> NDArray[np.bool_]:  # pragma: no cover - compiled
    """Whether each query's ball of ``reach * (1 + 1e-6) + margin_m`` stays inside ``box``
    (``x_low, x_high, y_low, y_high``) horizontally, edges marked ``infinite`` left out:
    ``enough & (reach * (1.0 + 1e-6) + margin_m < distance to the nearest closed edge)``."""
    exact = np.empty(queries.shape[0], np.bool_)
    for row in numba.prange(queries.shape[0]):
        x = queries[row, 0]
        y = queries[row, 1]
        edge = np.inf
        if not infinite[0]:
            edge = min(edge, x - box[0])
        if not infinite[1]:
            edge = min(edge, box[1] - x)
        if not infinite[2]:
            edge = min(edge, y - box[2])
        if not infinite[3]:
            edge = min(edge, box[3] - y)
        exact[row] = enough and reach[row] * (1.0 + 1e-6) + margin_m < edge
    return exact


@numba.njit(cache=True, nogil=True, parallel=True)
def _rows_of_keys(
    keys: NDArray[np.int64], row_keys: NDArray[np.int64], out: NDArray[np.int64]
) -> None:  # pragma: no cover - compiled
    last = row_keys.size - 1
    for i in numba.prange(keys.size):
        key = keys[i]
        position = min(np.searchsorted(row_keys, key), last)
        out[i] = position if row_keys[position] == key else -1


_COLUMN_TABLE_SLACK = 4
"""A table of the rows' columns is made when it has at most this many entries a row
(plus a few thousand): a tile's rows fill its columns, a sparse set would not."""


def _column_table(row_keys: NDArray[np.int64]) -> tuple[NDArray[np.int64], int, int, int, int]:
    """Where each (x, y) column of the sorted ``row_keys`` starts (a dense table over the
    columns' rectangle), with the rectangle: ``(starts, x0, y0, nx, ny)``; ``nx = 0`` when
    the rectangle is too large for a table (or a key is negative)."""
    first, last = int(row_keys[0]), int(row_keys[-1])
    if first < 0:
        return np.empty(0, np.int64), 0, 0, 0, 0
    x0, x1 = first >> (2 * CELL_BITS), last >> (2 * CELL_BITS)
    low_y, high_y = _y_range(row_keys)
    nx, ny = x1 - x0 + 1, int(high_y) - int(low_y) + 1
    if nx * ny > _COLUMN_TABLE_SLACK * row_keys.size + 4096:
        return np.empty(0, np.int64), 0, 0, 0, 0
    return _column_starts(row_keys, x0, int(low_y), ny, nx * ny), x0, int(low_y), nx, ny


@numba.njit(cache=True, nogil=True, parallel=True)
def _y_range(row_keys: NDArray[np.int64]) -> tuple[int, int]:  # pragma: no cover - compiled
    mask = (1 << CELL_BITS) - 1
    low = mask
    high = 0
    for i in numba.prange(row_keys.size):
        y = (row_keys[i] >> CELL_BITS) & mask
        low = min(low, y)
        high = max(high, y)
    return low, high


@numba.njit(cache=True, nogil=True)
def _column_starts(
    row_keys: NDArray[np.int64], x0: int, y0: int, ny: int, n_columns: int
) -> NDArray[np.int64]:  # pragma: no cover - compiled
    """``starts[c]``: the first row of column ``c = (x - x0) * ny + (y - y0)`` or of the
    next present one (sorted keys: a column's rows are consecutive); ``starts[n_columns]``
    is the rows' count."""
    mask = (1 << CELL_BITS) - 1
    starts = np.empty(n_columns + 1, np.int64)
    column = 0
    for row in range(row_keys.size):
        key = row_keys[row]
        mine = ((key >> (2 * CELL_BITS)) - x0) * ny + (((key >> CELL_BITS) & mask) - y0)
        while column <= mine:
            starts[column] = row
            column += 1
    while column <= n_columns:
        starts[column] = row_keys.size
        column += 1
    return starts


@numba.njit(cache=True, nogil=True, parallel=True)
def _rows_of_keys_by_column(
    keys: NDArray[np.int64],
    row_keys: NDArray[np.int64],
    starts: NDArray[np.int64],
    x0: int,
    y0: int,
    nx: int,
    ny: int,
    out: NDArray[np.int64],
) -> None:  # pragma: no cover - compiled
    """:func:`_rows_of_keys` through the table of the rows' columns: a key's column gives
    its few candidate rows at once, where a search through every row made ~20 steps
    through memory far apart."""
    mask = (1 << CELL_BITS) - 1
    for i in numba.prange(keys.size):
        key = keys[i]
        found = -1
        if key >= 0:
            x = (key >> (2 * CELL_BITS)) - x0
            y = ((key >> CELL_BITS) & mask) - y0
            if 0 <= x < nx and 0 <= y < ny:
                column = x * ny + y
                low = starts[column]
                end = starts[column + 1]
                high = end
                while low < high:  # the column's first key not below (a wall's: many)
                    middle = (low + high) >> 1
                    if row_keys[middle] < key:
                        low = middle + 1
                    else:
                        high = middle
                if low < end and row_keys[low] == key:
                    found = low
        out[i] = found


def rows_of_keys(
    keys: NDArray[np.int64], row_keys: NDArray[np.int64], *, in_place: bool = False
) -> NDArray[np.int64]:
    """The row of every key in ``keys`` (any shape): its position in the sorted unique
    ``row_keys``, or -1 where it is not there. ``in_place``: written over ``keys`` (a
    C-contiguous int64 array), which is returned; a tile's neighbour lists are 80 bytes
    a voxel. Packed voxel keys of rows that fill their columns' rectangle (a tile's
    level-0 voxels) are found through a table of the columns (:func:`_column_table`,
    about 3x faster than searching every row); other keys by a search."""
    if in_place:
        if keys.dtype != np.int64 or not keys.flags.c_contiguous or not keys.flags.writeable:
            raise ValueError("keys: expected a writeable C-contiguous int64 array in place")
        rows = keys
    else:
        rows = np.empty(keys.shape, np.int64)
    if row_keys.size == 0:
        rows[...] = -1
        return rows
    sorted_keys = np.ascontiguousarray(row_keys, dtype=np.int64)
    flat = np.ascontiguousarray(keys, dtype=np.int64).reshape(-1)
    starts, x0, y0, nx, ny = _column_table(sorted_keys)
    if nx:  # each key is read before its row is written
        _rows_of_keys_by_column(flat, sorted_keys, starts, x0, y0, nx, ny, rows.reshape(-1))
    else:
        _rows_of_keys(flat, sorted_keys, rows.reshape(-1))
    return rows


@numba.njit(cache=True, nogil=True, parallel=True)
def _in_box(
    xyz: NDArray[np.float64], box: NDArray[np.float64]
) -> NDArray[np.bool_]:  # pragma: no cover
    inside = np.empty(xyz.shape[0], np.bool_)
    for row in numba.prange(xyz.shape[0]):
        x = xyz[row, 0]
        y = xyz[row, 1]
        inside[row] = x >= box[0] and x <= box[1] and y >= box[2] and y <= box[3]
    return inside


def rows_in_box(xyz: NDArray[np.float64], box: NDArray[np.float64]) -> NDArray[np.intp]:
    """The rows of ``xyz`` inside ``box`` (``x_low, x_high, y_low, y_high``, closed),
    ascending."""
    return np.flatnonzero(_in_box(xyz, np.ascontiguousarray(box, dtype=np.float64)))


@numba.njit(cache=True, nogil=True, parallel=True)
def put_rows(
    source: NDArray[np.generic], rows: NDArray[np.intp], out: NDArray[np.generic], offset: int
) -> None:  # pragma: no cover - compiled
    """``out[offset : offset + rows.size] = source[rows]`` for 2-D arrays."""
    for i in numba.prange(rows.size):
        for column in range(source.shape[1]):
            out[offset + i, column] = source[rows[i], column]


@numba.njit(cache=True, nogil=True, parallel=True)
def put_values(
    source: NDArray[np.generic], rows: NDArray[np.intp], out: NDArray[np.generic], offset: int
) -> None:  # pragma: no cover - compiled
    """``out[offset : offset + rows.size] = source[rows]`` for 1-D arrays."""
    for i in numba.prange(rows.size):
        out[offset + i] = source[rows[i]]


_BLOCK_ROWS = 1 << 15  # the least rows a thread counts on its own


@numba.njit(cache=True, nogil=True, parallel=True)
def distinct_values(
    values: NDArray[np.int64],
) -> tuple[NDArray[np.int64], NDArray[np.int64], bool]:  # pragma: no cover - compiled
    """``np.unique(values, return_inverse=True)`` of non-negative integers, by marking a
    table as large as the largest value (linear time), and whether ``values`` already
    are their distinct values in order (strictly increasing). Every pass on every
    thread: marks, blocks of the table counted apart and numbered from the counts
    summed before them, then each value's rank."""
    n = values.size
    largest = 0
    for i in numba.prange(n):
        largest = max(largest, values[i])
    present = np.zeros(largest + 1, np.bool_)
    for i in numba.prange(n):
        present[values[i]] = True  # every thread writes the same value
    size = largest + 1
    n_blocks = max(1, size // _BLOCK_ROWS)
    per_block = -(-size // n_blocks)
    counts = np.zeros(n_blocks, np.int64)
    for block in numba.prange(n_blocks):
        count = 0
        for j in range(block * per_block, min(size, (block + 1) * per_block)):
            count += present[j]
        counts[block] = count
    firsts = np.empty(n_blocks, np.int64)
    running = 0
    for block in range(n_blocks):
        firsts[block] = running
        running += counts[block]
    distinct = np.empty(running, np.int64)
    rank = np.empty(size, np.int64)
    for block in numba.prange(n_blocks):
        at = firsts[block]
        for j in range(block * per_block, min(size, (block + 1) * per_block)):
            if present[j]:
                distinct[at] = j
                rank[j] = at
                at += 1
    inverse = np.empty(n, np.int64)
    moved = 0
    for i in numba.prange(n):
        inverse[i] = rank[values[i]]
        if inverse[i] != i:
            moved += 1
    return distinct, inverse, running == n and moved == 0
