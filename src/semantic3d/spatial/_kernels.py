"""Compiled counting sorts that build a tile store: points grouped by tile, then by sub-cell.

Hand-written because binning is most of the cost of a store and numpy needs several
passes for it (a stable ``argsort`` of the tile ids, a gather of the 40-byte records, and
building those records in scan order first). A counting sort is one pass to count, a
prefix sum and one pass to scatter; it is stable, so each group keeps the scan's order and
the result is the one ``np.argsort(ids, kind="stable")`` gives.
"""

from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(cache=True, nogil=True)
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
) -> np.ndarray:  # pragma: no cover - compiled
    """Scatter point ``i`` to the records of group ``slots[i]`` (``n_slots``: dropped).

    Columns go straight from the chunk's arrays into the packed records, groups in slot
    order and scan order inside a group. ``labels`` and ``out_labels`` are empty when the
    points have none. Returns the points per slot.
    """
    n = slots.shape[0]
    counts = np.zeros(n_slots + 1, np.int64)
    for i in range(n):
        counts[slots[i]] += 1
    nexts = np.empty(n_slots + 1, np.int64)
    running = 0
    for slot in range(n_slots + 1):
        nexts[slot] = running
        running += counts[slot]
    with_labels = out_labels.shape[0] > 0
    for i in range(n):
        slot = slots[i]
        if slot == n_slots:
            continue
        j = nexts[slot]
        nexts[slot] = j + 1
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


@nb.njit(cache=True, nogil=True)
def sub_cell_order(
    xyz: np.ndarray,
    x0: float,
    y0: float,
    sub_m: float,
    n_sub: int,
    order: np.ndarray,
    offsets: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """A tile's points sub-cell by sub-cell: ``order`` (local indices) and ``offsets``.

    Sub-cell ``sx * n_sub + sy`` with ``sx = clip(floor((x - x0) / sub_m), 0, n_sub - 1)``
    (the expression :meth:`TileStore._box_indices` inverts); ``offsets`` has ``n_sub**2 + 1``
    entries, where each sub-cell starts in ``order``.
    """
    n = xyz.shape[0]
    top = float(n_sub - 1)
    cells = np.empty(n, np.int64)
    offsets[:] = 0
    for i in range(n):
        sx = min(max(np.floor((xyz[i, 0] - x0) / sub_m), 0.0), top)
        sy = min(max(np.floor((xyz[i, 1] - y0) / sub_m), 0.0), top)
        cell = int(sx) * n_sub + int(sy)
        cells[i] = cell
        offsets[cell + 1] += 1
    for cell in range(n_sub * n_sub):
        offsets[cell + 1] += offsets[cell]
    nexts = offsets[:-1].copy()
    for i in range(n):
        cell = cells[i]
        order[nexts[cell]] = i
        nexts[cell] += 1


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
