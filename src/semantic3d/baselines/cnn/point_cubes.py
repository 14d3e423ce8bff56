"""Occupancy cubes centred exactly on each point (``CubeConfig.centring = "point"``).

Definition. At a scale of voxel edge ``v``, every point (of the tile and its halo, and
every query point) gets, per axis and in float64, ``f = (q - origin) / v``, its cell
``A = floor(f)`` (the cell of :func:`semantic3d.spatial.compute_cells`) and its fraction
``t = f - A``. Point ``q`` falls in voxel ``i`` (per axis) of the ``C``-voxel cube of
point ``p`` when::

    i = (A_q - A_p) + C/2 - (1 if t_q < t_p else 0),     0 <= i < C

which is ``floor(f_q - f_p) + C/2`` computed without cancellation: the cube is the
``C^3`` block of voxels of edge ``v`` whose corner ``(0, 0, 0)`` lies ``C/2`` voxels
below the point on each axis: the cube centred on its point, as the paper's footnote on
its cubes has it (Section 3.3). Only integers and comparisons of
per-point fractions decide, each computed from one point's own coordinates, so a tile
with a halo gives its points the very cubes the whole scan gives them.

Algorithm. Voxel ``i`` of the cube spans two cells of the scan's grid per axis: the upper
part (``t >= t_p``) of cell ``A_p + i - C/2`` and the lower part (``t < t_p``) of the
next cell up; cell ``c`` feeds voxel ``c - A_p + C/2`` with its upper part and the voxel
below with its lower part. In 3D a cell is thus cut by the point's split ``t_p``
into 8 orthant pieces, each feeding one voxel. For every occupied cell we keep a small
exact summary answering "which of the 8 orthants of split ``s`` hold a point": the union
of the cell's 8 Pareto skylines (the fractions not dominated in each orthant direction).
If a point lies in an orthant, the skyline point dominating it in that orthant's
direction lies there too, so the summary's orthant mask is the cell's. For a point and a
scale, the ``(C+1)^2`` columns of cells around it are found with one binary search each
in the sorted keys (as the corner-centred :func:`~.cubes.fill_cubes` does), each
occupied cell's 8-bit mask is computed from its summary, and its bits are scattered into
the cube.

The kernels are hand-written (numba): no library answers orthant-occupancy queries per
cell, and the generic route (every neighbour within the cube, from a k-d tree, marked
one by one) visits every point of a 6.4 m block per query and scale
(``benchmarks/bench_cnn.py`` measures both).

Cost. Per point and scale, ``(C+1)^2`` binary searches and a pass over the summaries of
the occupied cells of the block. Cells of more than :data:`FILTERED_ROWS` rows also keep
per-axis bounds and 8 directional maxima of their fractions, which rule out most empty
orthants without a scan, and their rows are stored in a spread-out order, so the scan
stops after a few rows once every orthant still possible is found. Summaries are small
where points fill a cell's volume (vegetation), but a surface tilted against all three
axes is its own skyline: a cell whose skyline in some direction passes
:data:`SKYLINE_MAX_POINTS` rows keeps all of its points. Dense surfaces therefore cost
more than sparse scans (``docs/baseline_cnn.md`` has the figures). The fractions are kept
in float64 (24 bytes a summary point a scale).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numba
import numpy as np
from numpy.typing import NDArray

from semantic3d.core.errors import ShapeError
from semantic3d.spatial.voxels import CELL_BITS, CELL_OFFSET, compute_cells, pack_keys

__all__ = [
    "FILTERED_ROWS",
    "SKYLINE_MAX_POINTS",
    "CellSummaries",
    "build_cell_summaries",
    "compute_point_anchors",
    "fill_point_cubes",
]

SKYLINE_MAX_POINTS = 64
"""A cell whose skyline in some direction passes this many points keeps all of its points
(a surface tilted against all three axes is its own skyline; the search would cost more
than it saves)."""

FILTERED_ROWS = 8
"""Cells of more summary rows also keep per-axis bounds and 8 directional maxima, which
rule out most empty orthants without a scan."""


@dataclass(frozen=True, slots=True)
class CellSummaries:
    """Per occupied cell of one scale, the fractions answering its orthant queries.

    Attributes:
        keys: sorted unique packed keys of the occupied cells (as :class:`~.cubes.Occupancy`).
        starts: ``(n_cells + 1,)`` offsets of each cell's rows in ``fractions``.
        fractions: ``(m, 3)`` float64 fractions ``t`` of the summary points.
        filter_rows: ``(n_cells,)`` row of each cell in ``filters``, -1 for cells of at
            most :data:`FILTERED_ROWS` summary rows.
        filters: ``(k, 14)`` per filtered cell: min and max of ``t`` per axis, then for
            each orthant direction ``d`` the largest ``sum(d * t)`` over the cell's points.
    """

    keys: NDArray[np.int64]
    starts: NDArray[np.int64]
    fractions: NDArray[np.float64]
    filter_rows: NDArray[np.int64]
    filters: NDArray[np.float64]


def compute_point_anchors(
    xyz: NDArray[np.float64], *, origin: NDArray[np.float64], voxel_size_m: float
) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """``(cells, fractions)`` of ``(n, 3)`` points: ``A = floor(f)`` and ``t = f - A``,
    ``f = (xyz - origin) / voxel_size_m`` in float64 (the definition's only float step)."""
    cells = compute_cells(xyz, origin=origin, voxel_size_m=voxel_size_m)  # checks the extent
    scaled = (xyz - origin) / voxel_size_m  # the same expression compute_cells floors
    return cells, scaled - cells


def build_cell_summaries(
    xyz: NDArray[np.float64], *, origin: NDArray[np.float64], voxel_size_m: float
) -> CellSummaries:
    """The occupied cells of ``(n, 3)`` float64 points at one scale, with their summaries."""
    cells, fractions = compute_point_anchors(xyz, origin=origin, voxel_size_m=voxel_size_m)
    keys = pack_keys(cells)
    order = np.argsort(keys, kind="stable")
    keys = keys[order]
    fractions = np.ascontiguousarray(fractions[order])
    if keys.size == 0:
        empty = np.zeros(0, np.int64)
        return CellSummaries(
            keys, np.zeros(1, np.int64), fractions.reshape(0, 3), empty, np.zeros((0, 14))
        )
    first = np.flatnonzero(np.concatenate([[True], keys[1:] != keys[:-1]]))
    bounds = np.append(first, keys.size).astype(np.int64)
    keep = np.zeros(keys.size, np.bool_)
    _mark_skylines(fractions, bounds, SKYLINE_MAX_POINTS, keep)
    kept_before = np.concatenate([[0], np.cumsum(keep)])
    starts = kept_before[bounds].astype(np.int64)
    kept = fractions[keep]
    kept = kept[_spread_order(kept, starts, FILTERED_ROWS)]
    filtered = np.diff(starts) > FILTERED_ROWS
    filter_rows = np.where(filtered, np.cumsum(filtered) - 1, -1).astype(np.int64)
    filters = np.empty((int(filtered.sum()), 14))
    _compute_filters(kept, starts, filter_rows, filters)
    return CellSummaries(keys[first], starts, kept, filter_rows, filters)


def fill_point_cubes(
    summaries: Sequence[CellSummaries],
    xyz: NDArray[np.float64],
    *,
    origin: NDArray[np.float64],
    voxel_sizes_m: Sequence[float],
    cube_voxels: int,
    out: NDArray[np.float32] | None = None,
) -> NDArray[np.float32]:
    """``(n, n_scales, C, C, C)`` float32 occupancy (0 or 1) of the cubes centred on ``xyz``.

    Args:
        summaries: per scale, the cells of the tile and its halo
            (:func:`build_cell_summaries` with the same origin and voxel size).
        xyz: ``(n, 3)`` float64 points whose cubes are wanted.
        origin: the scan's grid anchor.
        voxel_sizes_m: voxel edge of each scale.
        cube_voxels: ``C`` (even).
        out: an array of that shape to fill (reused between batches), else a new one.

    Axis order of a cube is x, y, z.
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ShapeError(f"xyz: expected (n, 3) coordinates, found {xyz.shape}")
    n_scales = len(voxel_sizes_m)
    if len(summaries) != n_scales:
        raise ShapeError(f"summaries: expected one per scale ({n_scales}), found {len(summaries)}")
    origin = np.asarray(origin, dtype=np.float64).reshape(3)
    shape = (xyz.shape[0], n_scales, cube_voxels, cube_voxels, cube_voxels)
    if out is None:
        out = np.empty(shape, np.float32)
    elif out.shape != shape or out.dtype != np.float32 or not out.flags.c_contiguous:
        raise ShapeError(f"out: expected a C-contiguous float32 {shape}, found {out.shape}")
    if xyz.shape[0] == 0:
        return out
    anchors = np.empty((xyz.shape[0], n_scales, 3), np.int64)
    splits = np.empty((xyz.shape[0], n_scales, 3), np.float64)
    for scale, size in enumerate(voxel_sizes_m):
        anchors[:, scale], splits[:, scale] = compute_point_anchors(
            xyz, origin=origin, voxel_size_m=float(size)
        )
    key_starts = np.zeros(n_scales + 1, np.int64)
    key_starts[1:] = np.cumsum([s.keys.size for s in summaries])
    row_offsets = np.zeros(n_scales + 1, np.int64)
    row_offsets[1:] = np.cumsum([s.fractions.shape[0] for s in summaries])
    # One flat array per field: numba takes no tuple of arrays of varying length cheaply.
    keys = np.concatenate([s.keys for s in summaries] + [np.zeros(1, np.int64)])
    starts = np.concatenate(
        [s.starts[:-1] + row_offsets[i] for i, s in enumerate(summaries)] + [row_offsets[-1:]]
    )
    fractions = np.concatenate([s.fractions for s in summaries] + [np.zeros((1, 3))])
    filter_offsets = np.cumsum([0] + [s.filters.shape[0] for s in summaries])
    filter_rows = np.concatenate(
        [
            np.where(s.filter_rows < 0, -1, s.filter_rows + filter_offsets[i])
            for i, s in enumerate(summaries)
        ]
        + [np.full(1, -1, np.int64)]
    )
    filters = np.concatenate([s.filters for s in summaries] + [np.zeros((1, 14))])
    _fill_point(
        keys,
        key_starts,
        starts,
        fractions,
        filter_rows,
        filters,
        anchors,
        splits,
        cube_voxels,
        out,
    )
    return out


@numba.njit(cache=True, nogil=True, parallel=True)
def _spread_order(
    fractions: NDArray[np.float64], starts: NDArray[np.int64], min_rows: int
) -> NDArray[np.int64]:  # pragma: no cover - compiled
    """A permutation putting each cell's rows (cells of more than ``min_rows``) in a
    spread-out order: along a Morton curve of the fractions, taken in bit-reversed rank
    order (the first rows lie in different parts of the cell), so that a scan finds every
    non-empty orthant after a few rows and stops."""
    order = np.arange(fractions.shape[0])
    for cell in numba.prange(starts.size - 1):
        lo = starts[cell]
        n = starts[cell + 1] - lo
        if n <= min_rows:
            continue
        codes = np.empty(n, np.int64)
        for r in range(n):
            code = 0
            for bit in range(9, -1, -1):
                for axis in range(3):
                    level = min(int(fractions[lo + r, axis] * 1024.0), 1023)
                    code = (code << 1) | ((level >> bit) & 1)
            codes[r] = code
        curve = np.argsort(codes, kind="mergesort")
        bits = 1
        while (1 << bits) < n:
            bits += 1
        out = lo
        for rank in range(1 << bits):
            reversed_rank = 0
            for bit in range(bits):
                reversed_rank |= ((rank >> bit) & 1) << (bits - 1 - bit)
            if reversed_rank < n:
                order[out] = lo + curve[reversed_rank]
                out += 1
    return order


@numba.njit(cache=True, nogil=True, parallel=True)
def _compute_filters(
    fractions: NDArray[np.float64],
    starts: NDArray[np.int64],
    filter_rows: NDArray[np.int64],
    filters: NDArray[np.float64],
) -> None:  # pragma: no cover - compiled
    for cell in numba.prange(filter_rows.size):
        row = filter_rows[cell]
        if row < 0:
            continue
        for axis in range(3):
            filters[row, axis] = np.inf
            filters[row, 3 + axis] = -np.inf
        for direction in range(8):
            filters[row, 6 + direction] = -np.inf
        for r in range(starts[cell], starts[cell + 1]):
            tx = fractions[r, 0]
            ty = fractions[r, 1]
            tz = fractions[r, 2]
            filters[row, 0] = min(filters[row, 0], tx)
            filters[row, 1] = min(filters[row, 1], ty)
            filters[row, 2] = min(filters[row, 2], tz)
            filters[row, 3] = max(filters[row, 3], tx)
            filters[row, 4] = max(filters[row, 4], ty)
            filters[row, 5] = max(filters[row, 5], tz)
            for direction in range(8):
                total = _signed_sum(direction, tx, ty, tz)
                filters[row, 6 + direction] = max(filters[row, 6 + direction], total)


@numba.njit(inline="always")
def _signed_sum(direction: int, x: float, y: float, z: float) -> float:  # pragma: no cover
    """``d . t`` for the orthant direction ``d`` of code ``direction`` (bit set: +1),
    always summed in the same order: float addition is monotone, so a point of the
    orthant ``t >= s`` (in ``d``'s sense) has ``_signed_sum(t) >= _signed_sum(s)``."""
    a = x if direction & 1 else -x
    b = y if direction & 2 else -y
    c = z if direction & 4 else -z
    return (a + b) + c


@numba.njit(cache=True, nogil=True, parallel=True)
def _mark_skylines(
    fractions: NDArray[np.float64],
    bounds: NDArray[np.int64],
    max_kept: int,
    keep: NDArray[np.bool_],
) -> None:  # pragma: no cover - compiled
    """``keep[r]``: row ``r`` is in the union of its cell's 8 skylines (cells of
    ``bounds[c]:bounds[c+1]``); a cell whose skyline in some direction passes
    ``max_kept`` rows keeps every row."""
    for cell in numba.prange(bounds.size - 1):
        lo = bounds[cell]
        hi = bounds[cell + 1]
        n = hi - lo
        if n <= 8:
            keep[lo:hi] = True
            continue
        signed = np.empty((n, 3))
        kept = np.empty(n, np.int64)
        flags = np.zeros(n, np.bool_)
        too_many = False
        for direction in range(8):
            for axis in range(3):
                sign = 1.0 if (direction >> axis) & 1 else -1.0
                for r in range(n):
                    signed[r, axis] = sign * fractions[lo + r, axis]
            # A row dominating another has a larger sum: it is visited first, so each
            # row is dropped only when a kept row dominates it (the kept rows cover all).
            order = np.argsort(-(signed[:, 0] + signed[:, 1] + signed[:, 2]))
            n_kept = 0
            for r in order:
                covered = False
                for k in range(n_kept):
                    other = kept[k]
                    if (
                        signed[other, 0] >= signed[r, 0]
                        and signed[other, 1] >= signed[r, 1]
                        and signed[other, 2] >= signed[r, 2]
                    ):
                        covered = True
                        break
                if not covered:
                    kept[n_kept] = r
                    n_kept += 1
                    flags[r] = True
                    if n_kept > max_kept:
                        too_many = True
                        break
            if too_many:
                break
        for r in range(n):
            keep[lo + r] = too_many or flags[r]


@numba.njit(cache=True, nogil=True, parallel=True)
def _fill_point(
    keys: NDArray[np.int64],
    key_starts: NDArray[np.int64],
    starts: NDArray[np.int64],
    fractions: NDArray[np.float64],
    filter_rows: NDArray[np.int64],
    filters: NDArray[np.float64],
    anchors: NDArray[np.int64],
    splits: NDArray[np.float64],
    size: int,
    out: NDArray[np.float32],
) -> None:  # pragma: no cover - compiled
    n = anchors.shape[0]
    n_scales = anchors.shape[1]
    half = size // 2
    x_shift = 2 * CELL_BITS
    for point in numba.prange(n):
        for scale in range(n_scales):
            cube = out[point, scale]
            cube[:] = 0.0
            lo = key_starts[scale]
            hi = key_starts[scale + 1]
            if lo == hi:
                continue
            sx = splits[point, scale, 0]
            sy = splits[point, scale, 1]
            sz = splits[point, scale, 2]
            bx = anchors[point, scale, 0] - half + CELL_OFFSET
            by = anchors[point, scale, 1] - half + CELL_OFFSET
            bz = anchors[point, scale, 2] - half + CELL_OFFSET
            for ci in range(size + 1):
                # Which halves of the cell land inside the cube: bit 0 the lower part
                # (voxel ci - 1), bit 1 the upper part (voxel ci).
                x_parts = 2 if ci == 0 else (1 if ci == size else 3)
                for cj in range(size + 1):
                    y_parts = 2 if cj == 0 else (1 if cj == size else 3)
                    first = ((bx + ci) << x_shift) | ((by + cj) << CELL_BITS) | bz
                    last = first + size + 1
                    a = lo  # lower bound of ``first`` in keys[lo:hi]
                    b = hi
                    while a < b:
                        m = (a + b) >> 1
                        if keys[m] < first:
                            a = m + 1
                        else:
                            b = m
                    while a < hi and keys[a] < last:
                        ck = keys[a] - first
                        z_parts = 2 if ck == 0 else (1 if ck == size else 3)
                        wanted = 0  # orthant codes: bit 0 upper x, bit 1 upper y, bit 2 upper z
                        for code in range(8):
                            if (
                                (x_parts >> (code & 1)) & 1
                                and (y_parts >> ((code >> 1) & 1)) & 1
                                and (z_parts >> (code >> 2)) & 1
                            ):
                                wanted |= 1 << code
                        row = filter_rows[a]
                        if row >= 0:  # drop the orthants the bounds prove empty
                            for code in range(8):
                                if (wanted >> code) & 1 and not (
                                    (filters[row, 3] >= sx if code & 1 else filters[row, 0] < sx)
                                    and (
                                        filters[row, 4] >= sy if code & 2 else filters[row, 1] < sy
                                    )
                                    and (
                                        filters[row, 5] >= sz if code & 4 else filters[row, 2] < sz
                                    )
                                    and filters[row, 6 + code] >= _signed_sum(code, sx, sy, sz)
                                ):
                                    wanted &= ~(1 << code)
                        mask = 0
                        if wanted == 0:
                            a += 1
                            continue
                        for r in range(starts[a], starts[a + 1]):
                            code = 0
                            if fractions[r, 0] >= sx:
                                code = 1
                            if fractions[r, 1] >= sy:
                                code |= 2
                            if fractions[r, 2] >= sz:
                                code |= 4
                            mask |= 1 << code
                            if mask & wanted == wanted:
                                break
                        mask &= wanted
                        if mask:
                            for code in range(8):
                                if (mask >> code) & 1:
                                    cube[
                                        ci - 1 + (code & 1),
                                        cj - 1 + ((code >> 1) & 1),
                                        ck - 1 + (code >> 2),
                                    ] = 1.0
                        a += 1
