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

from typing import Any

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
def sub_cell_codes(
    xyz: np.ndarray, x0: float, y0: float, sub_m: float, n_sub: int, codes: np.ndarray
) -> None:  # pragma: no cover - compiled
    """Each point's sub-cell of its tile, written into ``codes`` (uint16: ``n_sub`` <= 256).

    Sub-cell ``sx * n_sub + sy`` with ``sx = clip(floor((x - x0) / sub_m), 0, n_sub - 1)``
    (the expression :meth:`TileStore._box_indices` inverts). A tile's points may come in
    windows: a point's code depends on nothing but the point.
    """
    top = float(n_sub - 1)
    for i in nb.prange(xyz.shape[0]):
        sx = min(max(np.floor((xyz[i, 0] - x0) / sub_m), 0.0), top)
        sy = min(max(np.floor((xyz[i, 1] - y0) / sub_m), 0.0), top)
        codes[i] = int(sx) * n_sub + int(sy)


@nb.njit(cache=True, nogil=True, parallel=True)
def order_by_code(
    codes: np.ndarray, n_codes: int, order: np.ndarray, offsets: np.ndarray, n_threads: int
) -> None:  # pragma: no cover - compiled
    """A stable counting sort of ``codes`` (values ``0..n_codes-1``): ``order`` (int32
    positions, code by code, each code's in their order) and ``offsets`` (``n_codes + 1``
    entries, where each code starts in ``order``): ``np.argsort(codes, kind="stable")``.

    As :func:`stable_destinations` (blocks counted on every thread, the same order for any
    ``n_threads``), but each block writes its positions straight into ``order``: no
    8-byte destination per element beside the 2-byte codes.
    """
    n = codes.shape[0]
    n_blocks = max(1, min(4 * n_threads, n // _BLOCK_POINTS))
    per_block = -(-n // n_blocks)
    counts = np.zeros((n_blocks, n_codes), np.int64)
    for block in nb.prange(n_blocks):
        for i in range(block * per_block, min(n, (block + 1) * per_block)):
            counts[block, codes[i]] += 1
    starts = np.empty((n_blocks, n_codes), np.int64)
    running = 0
    offsets[0] = 0
    for code in range(n_codes):
        for block in range(n_blocks):
            starts[block, code] = running
            running += counts[block, code]
        offsets[code + 1] = running
    for block in nb.prange(n_blocks):
        nexts = starts[block].copy()
        for i in range(block * per_block, min(n, (block + 1) * per_block)):
            code = codes[i]
            order[nexts[code]] = i
            nexts[code] += 1


@nb.njit(cache=True, nogil=True, inline="always")
def _cell(value: Any, origin: Any, cell_m: Any) -> Any:  # pragma: no cover - compiled
    """``floor((value - origin) / cell_m)`` as an integer, as numpy computes it."""
    return np.int64(np.floor((value - origin) / cell_m))


@nb.njit(cache=True, nogil=True, parallel=True)
def tile_keys_extent(
    xyz: np.ndarray,
    origin_x: float,
    origin_y: float,
    cell_m: float,
    cells_per_tile: int,
    keep: np.ndarray,
) -> tuple[np.ndarray, int, int, int, int, int]:  # pragma: no cover - compiled
    """``(n, 2)`` tile keys ``floor((xy - origin) / cell_m) // cells_per_tile`` of every
    point (:meth:`~semantic3d.spatial.grid.TileGrid.tile_keys`), with the first row whose x or y is not finite
    (``n`` when none; its keys are 0) and the least and greatest x and y keys of the
    points ``keep`` marks (all when empty; the least above the greatest when none)."""
    n = xyz.shape[0]
    keys = np.empty((n, 2), np.int64)
    every = keep.shape[0] == 0
    bad = n
    x_min = np.iinfo(np.int64).max
    y_min = np.iinfo(np.int64).max
    x_max = np.iinfo(np.int64).min
    y_max = np.iinfo(np.int64).min
    for i in nb.prange(n):
        x, y = xyz[i, 0], xyz[i, 1]
        kx = np.int64(0)
        ky = np.int64(0)
        if np.isfinite(x) and np.isfinite(y):
            kx = _cell(x, origin_x, cell_m) // cells_per_tile
            ky = _cell(y, origin_y, cell_m) // cells_per_tile
        else:
            bad = min(bad, i)
        keys[i, 0] = kx
        keys[i, 1] = ky
        if every or keep[i]:
            x_min = min(x_min, int(kx))
            x_max = max(x_max, int(kx))
            y_min = min(y_min, int(ky))
            y_max = max(y_max, int(ky))
    return keys, bad, x_min, x_max, y_min, y_max


@nb.njit(cache=True, nogil=True, parallel=True)
def extent_slots(
    keys: np.ndarray, x_min: int, y_min: int, ny: int, keep: np.ndarray, dropped: int
) -> np.ndarray:  # pragma: no cover - compiled
    """``(keys[:, 0] - x_min) * ny + keys[:, 1] - y_min`` of the points ``keep`` marks (all
    when empty), ``dropped`` for the others."""
    n = keys.shape[0]
    slots = np.empty(n, np.int64)
    every = keep.shape[0] == 0
    for i in nb.prange(n):
        if every or keep[i]:
            slots[i] = (keys[i, 0] - x_min) * ny + (keys[i, 1] - y_min)
        else:
            slots[i] = dropped
    return slots


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
    for i in nb.prange(xyz.shape[0]):
        cx = _cell(xyz[i, 0], origin_x, cell_m)
        cy = _cell(xyz[i, 1], origin_y, cell_m)
        codes[i] = _square_code(cx, cy, cells_per_tile, depth)
    return codes


@nb.njit(cache=True, nogil=True, inline="always")
def _square_code(cx: Any, cy: Any, cells_per_tile: Any, depth: Any) -> Any:  # pragma: no cover
    """Morton code of cell ``(cx, cy)``'s square in its tile (x's bits above y's at every
    level)."""
    side = np.int64(1) << depth
    sx = (cx - (cx // cells_per_tile) * cells_per_tile) * side // cells_per_tile
    sy = (cy - (cy // cells_per_tile) * cells_per_tile) * side // cells_per_tile
    code = np.int64(0)
    for bit in range(depth):
        code |= ((sx >> bit) & 1) << (2 * bit + 1)
        code |= ((sy >> bit) & 1) << (2 * bit)
    return code


@nb.njit(cache=True, nogil=True, parallel=True)
def tile_places(
    xyz: np.ndarray,
    origin_x: float,
    origin_y: float,
    cell_m: float,
    cells_per_tile: int,
    depth: int,
    relative_to: np.ndarray,
    relative: np.ndarray,
    tiles: np.ndarray,
    codes: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """One pass over the points: ``relative = float32(xyz - relative_to)``, ``tiles`` the
    packed tile keys (``x << 32`` plus ``y``) and ``codes`` the squares' codes at
    ``depth``, as :func:`tile_keys_extent` and :func:`tile_cell_codes` compute them."""
    for i in nb.prange(xyz.shape[0]):
        for column in range(3):
            relative[i, column] = np.float32(xyz[i, column] - relative_to[column])
        cx = _cell(xyz[i, 0], origin_x, cell_m)
        cy = _cell(xyz[i, 1], origin_y, cell_m)
        tiles[i] = ((cx // cells_per_tile) << 32) + cy // cells_per_tile
        codes[i] = _square_code(cx, cy, cells_per_tile, depth)


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


@nb.njit(cache=True, nogil=True, parallel=True)
def copy_columns(
    xyz: np.ndarray,
    labels: np.ndarray,
    index: np.ndarray,
    out_xyz: np.ndarray,
    out_labels: np.ndarray,
    out_index: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """Contiguous copies of the strided columns of packed records, on every thread
    (``labels`` empty: no labels to copy; ``out_xyz`` empty: no coordinates)."""
    with_labels = labels.shape[0] > 0
    with_xyz = out_xyz.shape[0] > 0
    for i in nb.prange(index.shape[0]):
        if with_xyz:
            out_xyz[i, 0] = xyz[i, 0]
            out_xyz[i, 1] = xyz[i, 1]
            out_xyz[i, 2] = xyz[i, 2]
        out_index[i] = index[i]
        if with_labels:
            out_labels[i] = labels[i]


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


@nb.njit(cache=True, nogil=True, parallel=True)
def cell_coordinates(
    xyz: np.ndarray, origin: np.ndarray, size: float, limit: float
) -> tuple[np.ndarray, int]:  # pragma: no cover - compiled
    """``(n, 3)`` int64 ``floor((xyz - origin) / size)`` (numpy's arithmetic), and how many
    coordinates fall outside ``-limit..limit`` (or are not numbers); those are left 0."""
    n = xyz.shape[0]
    cells = np.empty((n, 3), np.int64)
    outside = 0
    for i in nb.prange(n):
        for axis in range(3):
            cell = np.floor((xyz[i, axis] - origin[axis]) / size)
            if cell >= -limit and cell <= limit:
                cells[i, axis] = np.int64(cell)
            else:
                cells[i, axis] = 0
                outside += 1
    return cells, outside


@nb.njit(cache=True, nogil=True, parallel=True)
def packed_keys(cells: np.ndarray, offset: int, bits: int) -> np.ndarray:  # pragma: no cover
    """``((x + offset) << 2 bits) | ((y + offset) << bits) | (z + offset)`` of every row."""
    keys = np.empty(cells.shape[0], np.int64)
    for i in nb.prange(cells.shape[0]):
        keys[i] = (
            ((cells[i, 0] + offset) << (2 * bits))
            | ((cells[i, 1] + offset) << bits)
            | (cells[i, 2] + offset)
        )
    return keys


_RADIX_BITS = 11  # the most bits sorted in one pass (2048 slots)


@nb.njit(cache=True, nogil=True, parallel=True)
def _key_spans(keys: np.ndarray, bits: int) -> np.ndarray:  # pragma: no cover - compiled
    """Smallest and largest x, y and z parts of the packed keys: ``[lo x, lo y, lo z, hi x,
    hi y, hi z]``."""
    n = keys.shape[0]
    n_blocks = max(1, n // _BLOCK_POINTS)
    per_block = -(-n // n_blocks)
    mask = (np.int64(1) << bits) - 1
    partial = np.empty((n_blocks, 6), np.int64)
    for block in nb.prange(n_blocks):
        low_x = low_y = low_z = np.int64(1) << 62
        high_x = high_y = high_z = np.int64(-1)
        for i in range(block * per_block, min(n, (block + 1) * per_block)):
            key = keys[i]
            x, y, z = key >> (2 * bits), (key >> bits) & mask, key & mask
            low_x, low_y, low_z = min(low_x, x), min(low_y, y), min(low_z, z)
            high_x, high_y, high_z = max(high_x, x), max(high_y, y), max(high_z, z)
        partial[block, 0], partial[block, 1], partial[block, 2] = low_x, low_y, low_z
        partial[block, 3], partial[block, 4], partial[block, 5] = high_x, high_y, high_z
    spans = partial[0].copy()
    for block in range(1, n_blocks):
        for part in range(3):
            spans[part] = min(spans[part], partial[block, part])
            spans[3 + part] = max(spans[3 + part], partial[block, 3 + part])
    return spans


@nb.njit(cache=True, nogil=True, parallel=True)
def _compact_keys(
    keys: np.ndarray, bits: int, spans: np.ndarray, y_shift: int, x_shift: int
) -> np.ndarray:  # pragma: no cover - compiled
    """The keys with each part less its smallest, packed tight (the same order)."""
    mask = (np.int64(1) << bits) - 1
    compact = np.empty(keys.shape[0], np.int64)
    for i in nb.prange(keys.shape[0]):
        key = keys[i]
        compact[i] = (
            (((key >> (2 * bits)) - spans[0]) << x_shift)
            | ((((key >> bits) & mask) - spans[1]) << y_shift)
            | ((key & mask) - spans[2])
        )
    return compact


@nb.njit(cache=True, nogil=True, parallel=True)
def _radix_digits(
    compact: np.ndarray, shift: int, mask: int, out: np.ndarray
) -> None:  # pragma: no cover
    for i in nb.prange(compact.shape[0]):
        out[i] = (compact[i] >> shift) & mask


@nb.njit(cache=True, nogil=True, parallel=True)
def _radix_place(
    destination: np.ndarray,
    compact: np.ndarray,
    order: np.ndarray,
    out_compact: np.ndarray,
    out_order: np.ndarray,
) -> None:  # pragma: no cover - compiled
    for i in nb.prange(destination.shape[0]):
        out_compact[destination[i]] = compact[i]
        out_order[destination[i]] = order[i]


@nb.njit(cache=True, nogil=True, parallel=True)
def group_order(
    groups: np.ndarray, n_groups: int, n_threads: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """``np.argsort(groups, kind="stable")`` of ids ``0..n_groups-1``, each group's bounds
    in it (``n_groups + 1``) and every element's place in its group: one stable counting
    sort (:func:`stable_destinations`)."""
    n = groups.shape[0]
    destination, totals = stable_destinations(groups, max(0, n_groups - 1), n_threads)
    bounds = np.zeros(n_groups + 1, np.int64)
    for group in range(n_groups):
        bounds[group + 1] = bounds[group] + totals[group]
    order = np.empty(n, np.int64)
    local = np.empty(n, np.int64)
    for i in nb.prange(n):
        order[destination[i]] = i
        local[i] = destination[i] - bounds[groups[i]]
    return order, bounds, local


@nb.njit(cache=True, nogil=True)
def key_order(keys: np.ndarray, bits: int, n_threads: int) -> np.ndarray:  # pragma: no cover
    """``np.argsort(keys, kind="stable")`` of packed keys (three parts of ``bits`` bits),
    on every thread: a least-significant-digit radix sort of the keys with each part less
    its smallest (so only the bits the keys span are sorted), each pass a stable counting
    sort (:func:`stable_destinations`). A stable order is unique: it does not depend on
    the threads."""
    n = keys.shape[0]
    order = np.arange(n).astype(np.int64)
    if n < 2:
        return order
    spans = _key_spans(keys, bits)
    z_bits = _bit_length(spans[5] - spans[2])
    y_bits = _bit_length(spans[4] - spans[1])
    x_bits = _bit_length(spans[3] - spans[0])
    total = x_bits + y_bits + z_bits
    if total == 0:
        return order
    compact = _compact_keys(keys, bits, spans, z_bits, y_bits + z_bits)
    n_passes = -(-total // _RADIX_BITS)
    digit_bits = -(-total // n_passes)
    mask = (1 << digit_bits) - 1
    digits = np.empty(n, np.int64)
    other_compact = np.empty(n, np.int64)
    other_order = np.empty(n, np.int64)
    for step in range(n_passes):
        _radix_digits(compact, step * digit_bits, mask, digits)
        destination, _ = stable_destinations(digits, mask + 1, n_threads)
        _radix_place(destination, compact, order, other_compact, other_order)
        compact, other_compact = other_compact, compact
        order, other_order = other_order, order
    return order


@nb.njit(cache=True, nogil=True)
def _bit_length(value: int) -> int:  # pragma: no cover - compiled
    length = 0
    while value > 0:
        value >>= 1
        length += 1
    return length


@nb.njit(cache=True, nogil=True, parallel=True)
def run_starts(keys: np.ndarray, order: np.ndarray) -> np.ndarray:  # pragma: no cover
    """Where each run of equal keys starts in ``keys[order]`` (``order`` sorting them),
    with the total length appended; blocks of the order on every thread."""
    n = order.shape[0]
    if n == 0:
        return np.zeros(1, np.int64)
    n_blocks = max(1, n // _BLOCK_POINTS)
    per_block = -(-n // n_blocks)
    counts = np.zeros(n_blocks, np.int64)
    for block in nb.prange(n_blocks):
        count = 0
        for j in range(max(1, block * per_block), min(n, (block + 1) * per_block)):
            if keys[order[j]] != keys[order[j - 1]]:
                count += 1
        counts[block] = count
    firsts = np.empty(n_blocks, np.int64)
    running = 1  # the first run starts at 0
    for block in range(n_blocks):
        firsts[block] = running
        running += counts[block]
    starts = np.empty(running + 1, np.int64)
    starts[0] = 0
    starts[running] = n
    for block in nb.prange(n_blocks):
        at = firsts[block]
        for j in range(max(1, block * per_block), min(n, (block + 1) * per_block)):
            if keys[order[j]] != keys[order[j - 1]]:
                starts[at] = j
                at += 1
    return starts
