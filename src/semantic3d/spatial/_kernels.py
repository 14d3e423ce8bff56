"""Compiled counting sorts that build a tile store: points grouped by tile, then by sub-cell.

Hand-written because binning is most of the cost of a store and numpy needs several
passes for it (a stable ``argsort`` of the tile ids, a gather of the 40-byte records, and
building those records in scan order first). A counting sort is one pass to count, a
prefix sum and one pass to scatter; it is stable, so each group keeps the scan's order and
the result is the one ``np.argsort(ids, kind="stable")`` gives.

The counts and the scatter run on every thread (blocks of points counted apart, then
placed from the counts summed before them), so binning does not wait on one core.
"""

from __future__ import annotations

import numba as nb
import numpy as np

_BLOCK_POINTS = 1 << 15  # the least points a thread counts on its own


@nb.njit(cache=True, nogil=True, parallel=True)
def stable_destinations(
    slots: np.ndarray, n_slots: int, n_threads: int
) -> tuple[np.ndarray, np.ndarray]:
    """Where a stable counting sort by ``slots`` (values ``0..n_slots``) puts each element,
    and the elements per slot (``n_slots + 1`` counts).

    Blocks of consecutive elements are counted on every thread, the counts summed slot by
    slot and block by block, and each block then places its own elements: the result is
    ``np.argsort(np.argsort(slots, kind="stable"))`` whatever the number of threads
    (``n_threads``, numba's threads: it sets the number of blocks).
    """
    n = slots.shape[0]
    n_blocks = max(1, min(4 * n_threads, n // _BLOCK_POINTS))
    per_block = -(-n // n_blocks)
    counts = np.zeros((n_blocks, n_slots + 1), np.int64)
    for block in nb.prange(n_blocks):
        for i in range(block * per_block, min(n, (block + 1) * per_block)):
            counts[block, slots[i]] += 1
    starts = np.empty((n_blocks, n_slots + 1), np.int64)
    totals = np.zeros(n_slots + 1, np.int64)
    running = 0
    for slot in range(n_slots + 1):
        for block in range(n_blocks):
            starts[block, slot] = running
            running += counts[block, slot]
            totals[slot] += counts[block, slot]
    destination = np.empty(n, np.int64)
    for block in nb.prange(n_blocks):
        nexts = starts[block].copy()
        for i in range(block * per_block, min(n, (block + 1) * per_block)):
            slot = slots[i]
            destination[i] = nexts[slot]
            nexts[slot] += 1
    return destination, totals


@nb.njit(cache=True, nogil=True, parallel=True)
def group_by_slot(
    slots: np.ndarray,
    n_slots: int,
    xyz: np.ndarray,
    index: np.ndarray,
    intensity: np.ndarray,
    rgb: np.ndarray,
    labels: np.ndarray,
    out_xyz: np.ndarray,
    out_index: np.ndarray,
    out_intensity: np.ndarray,
    out_rgb: np.ndarray,
    out_labels: np.ndarray,
    n_threads: int,
) -> np.ndarray:  # pragma: no cover - compiled
    """Scatter point ``i`` to the records of group ``slots[i]`` (``n_slots``: dropped).

    Columns go straight from the chunk's arrays into the packed records, groups in slot
    order and scan order inside a group. ``labels`` and ``out_labels`` are empty when the
    points have none. Returns the points per slot.
    """
    destination, counts = stable_destinations(slots, n_slots, n_threads)
    with_labels = out_labels.shape[0] > 0
    for i in nb.prange(slots.shape[0]):
        if slots[i] == n_slots:
            continue
        j = destination[i]
        out_xyz[j, 0] = xyz[i, 0]
        out_xyz[j, 1] = xyz[i, 1]
        out_xyz[j, 2] = xyz[i, 2]
        out_index[j] = index[i]
        out_intensity[j] = intensity[i]
        out_rgb[j, 0] = rgb[i, 0]
        out_rgb[j, 1] = rgb[i, 1]
        out_rgb[j, 2] = rgb[i, 2]
        if with_labels:
            out_labels[j] = labels[i]
    return counts[:n_slots]


@nb.njit(cache=True, nogil=True, parallel=True)
def sub_cell_order(
    xyz: np.ndarray,
    x0: float,
    y0: float,
    sub_m: float,
    n_sub: int,
    order: np.ndarray,
    offsets: np.ndarray,
    n_threads: int,
) -> None:  # pragma: no cover - compiled
    """A tile's points sub-cell by sub-cell: ``order`` (local indices) and ``offsets``.

    Sub-cell ``sx * n_sub + sy`` with ``sx = clip(floor((x - x0) / sub_m), 0, n_sub - 1)``
    (the expression :meth:`TileStore._box_indices` inverts); ``offsets`` has ``n_sub**2 + 1``
    entries, where each sub-cell starts in ``order``.
    """
    n = xyz.shape[0]
    top = float(n_sub - 1)
    cells = np.empty(n, np.int64)
    for i in nb.prange(n):
        sx = min(max(np.floor((xyz[i, 0] - x0) / sub_m), 0.0), top)
        sy = min(max(np.floor((xyz[i, 1] - y0) / sub_m), 0.0), top)
        cells[i] = int(sx) * n_sub + int(sy)
    n_cells = n_sub * n_sub
    destination, counts = stable_destinations(cells, n_cells, n_threads)
    offsets[0] = 0
    for cell in range(n_cells):
        offsets[cell + 1] = offsets[cell] + counts[cell]
    for i in nb.prange(n):
        order[destination[i]] = i


@nb.njit(cache=True, nogil=True, parallel=True)
def tile_keys(
    xyz: np.ndarray, origin_x: float, origin_y: float, cell_m: float, cells_per_tile: int
) -> np.ndarray:  # pragma: no cover - compiled
    """``(n, 2)`` ``floor((xy - origin) / cell_m) // cells_per_tile`` of every point, as
    numpy computes it (:meth:`~semantic3d.spatial.grid.TileGrid.tile_keys`)."""
    keys = np.empty((xyz.shape[0], 2), np.int64)
    for i in nb.prange(xyz.shape[0]):
        keys[i, 0] = np.int64(np.floor((xyz[i, 0] - origin_x) / cell_m)) // cells_per_tile
        keys[i, 1] = np.int64(np.floor((xyz[i, 1] - origin_y) / cell_m)) // cells_per_tile
    return keys


@nb.njit(cache=True, nogil=True, parallel=True)
def tile_cell_codes(
    xyz: np.ndarray,
    origin_x: float,
    origin_y: float,
    cell_m: float,
    cells_per_tile: int,
    depth: int,
) -> np.ndarray:  # pragma: no cover - compiled
    """``(n,)`` uint16 Morton code of every point's square in its tile cut into
    ``2**depth`` by ``2**depth`` squares of whole cells
    (:meth:`~semantic3d.spatial.grid.TileGrid.cell_codes`)."""
    codes = np.empty(xyz.shape[0], np.uint16)
    side = np.int64(1) << depth
    for i in nb.prange(xyz.shape[0]):
        cx = np.int64(np.floor((xyz[i, 0] - origin_x) / cell_m))
        cy = np.int64(np.floor((xyz[i, 1] - origin_y) / cell_m))
        sx = (cx - (cx // cells_per_tile) * cells_per_tile) * side // cells_per_tile
        sy = (cy - (cy // cells_per_tile) * cells_per_tile) * side // cells_per_tile
        code = np.int64(0)
        for bit in range(depth):  # x's bits above y's at every level
            code |= ((sx >> bit) & 1) << (2 * bit + 1)
            code |= ((sy >> bit) & 1) << (2 * bit)
        codes[i] = code
    return codes


@nb.njit(cache=True, nogil=True)
def xyz_label_rows(
    xyz: np.ndarray, labels: np.ndarray, out: np.ndarray
) -> None:  # pragma: no cover - compiled
    """``out[i] = (x, y, z, label)`` from the strided columns of packed records (numpy's
    copy of a 40-byte-strided (n, 3) view is ~4x slower)."""
    with_labels = labels.shape[0] > 0
    for i in range(xyz.shape[0]):
        out[i, 0] = xyz[i, 0]
        out[i, 1] = xyz[i, 1]
        out[i, 2] = xyz[i, 2]
        out[i, 3] = labels[i] if with_labels else 0.0


@nb.njit(cache=True, nogil=True)
def select_in_box(
    xyz: np.ndarray,
    order: np.ndarray,
    offsets: np.ndarray,
    n_sub: int,
    cells: np.ndarray,
    box: np.ndarray,
) -> np.ndarray:  # pragma: no cover - compiled
    """Local indices, ascending (scan order), of a tile's points inside ``box``.

    ``cells`` is ``(sx0, sx1, sy0, sy1)``, the sub-cells that can hold such points, or
    ``sx0 < 0`` to test every point; ``box`` is ``(x_min, y_min, x_max, y_max)``, edges
    included.
    """
    x_min, y_min, x_max, y_max = box[0], box[1], box[2], box[3]
    if cells[0] < 0:
        found = np.empty(xyz.shape[0], np.int64)
        count = 0
        for i in range(xyz.shape[0]):
            x, y = xyz[i, 0], xyz[i, 1]
            if x >= x_min and x <= x_max and y >= y_min and y <= y_max:
                found[count] = i
                count += 1
        return found[:count]
    sx0, sx1, sy0, sy1 = cells[0], cells[1], cells[2], cells[3]
    size = 0
    for sx in range(sx0, sx1 + 1):
        size += offsets[sx * n_sub + sy1 + 1] - offsets[sx * n_sub + sy0]
    found = np.empty(size, np.int64)
    count = 0
    for sx in range(sx0, sx1 + 1):
        for k in range(offsets[sx * n_sub + sy0], offsets[sx * n_sub + sy1 + 1]):
            i = order[k]
            x, y = xyz[i, 0], xyz[i, 1]
            if x >= x_min and x <= x_max and y >= y_min and y <= y_max:
                found[count] = i
                count += 1
    if count * 32 < xyz.shape[0]:
        return np.sort(found[:count])
    # Many points: back to scan order by marking them (linear, no sort).
    marked = np.zeros(xyz.shape[0], np.bool_)
    for k in range(count):
        marked[found[k]] = True
    count = 0
    for i in range(xyz.shape[0]):
        if marked[i]:
            found[count] = i
            count += 1
    return found[:count]
