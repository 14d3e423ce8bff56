"""Point-centred occupancy cubes on a torch device: the cubes of :mod:`.point_cubes`,
exactly, from the tile's cell summaries uploaded once.

The compiled CPU kernel answers, per point, scale and occupied cell of the point's block,
"which of the cell's 8 orthant pieces (cut by the point's split) hold a point" by scanning
the cell's summary rows until every piece still possible is found. A cell's summary has a
length of its own, so a batched form works on *pairs* (query, cell) instead, in plain
torch operations that run on any device:

1. **Cells of each block.** For every query and scale, the ``(C+1)^2`` columns of cells of
   its block; one ``torch.searchsorted`` per column bound in the scale's sorted keys (all
   scales at once, their key rows padded with the largest int64) gives each column's
   occupied cells; a CSR expansion (``repeat_interleave``) lists the pairs.
2. **Pieces wanted and possible.** Which pieces of a cell land inside the cube (a table
   per column and layer), less those the cell's bounds and directional maxima prove
   empty (:data:`~.point_cubes.FILTERED_ROWS`), with the very float64 comparisons and
   summation order of the compiled kernel; the filters only ever rule out empty pieces.
3. **Rows, in rounds.** The first 8 rows of every pair's cell (a cell of at most 8 rows is
   then done), then, for the pairs whose wanted pieces are not all found, the next rows in
   rounds of growing length (8-32, 32-128, ..., all): the summaries' spread-out row order
   finds most pieces in the first rounds, as the CPU kernel's early stop does.
4. **Scatter.** Each found piece sets its voxel (``index_fill_`` of ones: the same value
   whatever the order).

Every decision is an integer operation or a comparison of float64 values computed on the
host by the definition's one float step (:func:`~.point_cubes.compute_point_anchors`), so
the cubes equal the compiled kernel's bit for bit on every device (tested on the CPU
device in CI and on CUDA under the ``gpu`` marker). Work is chunked by a budget of pairs,
so memory is bounded whatever the batch. The summaries (integer keys and offsets, float64
fractions and filters) go to the device once per tile; a batch sends 48 bytes per point
and scale (its cells and splits) and its cubes are born on the device.

Needs the ``[torch]`` extra.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from semantic3d.core.errors import require

torch: Any = require("torch", "torch")

from semantic3d.baselines.cnn.cubes import CentringError, Occupancy  # noqa: E402
from semantic3d.baselines.cnn.point_cubes import (  # noqa: E402
    FILTERED_ROWS,
    compute_point_anchors,
)
from semantic3d.core.errors import ShapeError  # noqa: E402
from semantic3d.spatial.voxels import CELL_BITS, CELL_OFFSET  # noqa: E402

__all__ = ["DevicePointCubes", "compute_anchors", "pack_cubes", "unpack_cubes"]

_PAIR_BUDGET = {"cuda": 1 << 22, "cpu": 1 << 20}
"""(query, cell) pairs (or row visits) handled at once, ~250 bytes each at most: ~1 GB
on a GPU, ~250 MB on a CPU."""
_QUERY_BLOCK = {"cuda": 2048, "cpu": 256}
"""Queries whose block columns are searched together (fewer, larger kernels on a GPU)."""
_INT64_MAX = int(np.iinfo(np.int64).max)
_FIRST_ROWS = FILTERED_ROWS  # a cell of at most FILTERED_ROWS rows is done in the first round
_GROWTH = 4  # rows 8-32, 32-128, ...: fewer rounds than 2x, as few visits (measured)


def compute_anchors(
    xyz: NDArray[np.float64], *, origin: NDArray[np.float64], voxel_sizes_m: tuple[float, ...]
) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """``(n, n_scales, 3)`` cells and fractions of ``(n, 3)`` points at every scale (the
    host-side float64 step of the definition, :func:`~.point_cubes.compute_point_anchors`)."""
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ShapeError(f"xyz: expected (n, 3) coordinates, found {xyz.shape}")
    cells = np.empty((xyz.shape[0], len(voxel_sizes_m), 3), np.int64)
    fractions = np.empty((xyz.shape[0], len(voxel_sizes_m), 3), np.float64)
    for scale, size in enumerate(voxel_sizes_m):
        cells[:, scale], fractions[:, scale] = compute_point_anchors(
            xyz, origin=origin, voxel_size_m=float(size)
        )
    return cells, fractions


class DevicePointCubes:
    """A tile's point-centred :class:`~.cubes.Occupancy` held on a torch device.

    Args:
        occupancy: the tile and its halo, built with ``centring="point"``.
        device: where to hold it and make cubes (``"cuda"``, ``"cpu"``).
        cube_voxels: ``C`` (even).
        pair_budget: pairs handled at once (bounds the working memory; default by
            device type).
        query_block: queries whose blocks are searched together (default by device type).
    """

    def __init__(
        self,
        occupancy: Occupancy,
        *,
        device: Any,
        cube_voxels: int,
        pair_budget: int | None = None,
        query_block: int | None = None,
    ) -> None:
        if occupancy.summaries is None:
            raise CentringError(
                "occupancy: expected cell summaries for point-centred cubes, found an "
                'occupancy built for corner-centred ones (build_occupancy(..., centring="point"))'
            )
        self.device = torch.device(device)
        self.origin = occupancy.origin
        self.voxel_sizes_m = occupancy.voxel_sizes_m
        self.cube_voxels = cube_voxels
        kind = "cuda" if self.device.type == "cuda" else "cpu"
        self.pair_budget = max(int(pair_budget or _PAIR_BUDGET[kind]), 1)
        self.query_block = max(int(query_block or _QUERY_BLOCK[kind]), 1)
        summaries = occupancy.summaries
        n_scales = len(summaries)
        lengths = [s.keys.size for s in summaries]
        width = max(max(lengths, default=0), 1)
        padded = np.full((n_scales, width), _INT64_MAX, np.int64)
        for scale, s in enumerate(summaries):
            padded[scale, : s.keys.size] = s.keys
        key_starts = np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64)
        row_offsets = np.concatenate([[0], np.cumsum([s.fractions.shape[0] for s in summaries])])
        row_starts = np.concatenate(
            [s.starts[:-1] + row_offsets[i] for i, s in enumerate(summaries)]
            + [row_offsets[-1:].astype(np.int64)]
        ).astype(np.int64)
        filter_offsets = np.concatenate([[0], np.cumsum([s.filters.shape[0] for s in summaries])])
        filter_rows = np.concatenate(
            [
                np.where(s.filter_rows < 0, -1, s.filter_rows + filter_offsets[i])
                for i, s in enumerate(summaries)
            ]
            + [np.zeros(0, np.int64)]
        ).astype(np.int64)
        # A sentinel row and filter at the end: gathers of masked-out pairs read them.
        fractions = np.concatenate([s.fractions for s in summaries] + [np.zeros((1, 3))])
        filters = np.concatenate([s.filters for s in summaries] + [np.zeros((1, 14))])
        upload = _uploader(self.device)
        self._keys = upload(padded)
        self._key_starts = upload(key_starts)
        self._row_starts = upload(row_starts)
        self._fractions = upload(fractions)
        self._filter_rows = upload(filter_rows)
        self._filters = upload(filters)
        self._n_cells = int(key_starts[-1])
        self._tables = _Tables(cube_voxels, self.device)

    @property
    def n_scales(self) -> int:
        """Cubes per point."""
        return len(self.voxel_sizes_m)

    def anchors(self, xyz: NDArray[np.float64]) -> tuple[Any, Any]:
        """Cells and fractions of ``(n, 3)`` float64 points, on the device (send a tile's
        once, then :meth:`fill` slices of them)."""
        cells, fractions = compute_anchors(
            xyz, origin=self.origin, voxel_sizes_m=self.voxel_sizes_m
        )
        upload = _uploader(self.device)
        return upload(cells), upload(fractions)

    def fill_points(self, xyz: NDArray[np.float64], *, dtype: Any = None) -> Any:
        """``(n, n_scales, C, C, C)`` cubes (``dtype``, default float32) of ``(n, 3)``
        float64 points: :func:`~.point_cubes.fill_point_cubes`'s, on the device."""
        cells, fractions = self.anchors(xyz)
        return self.fill(cells, fractions, dtype=dtype)

    def fill(self, cells: Any, fractions: Any, *, dtype: Any = None) -> Any:
        """Cubes of the points whose ``(n, n_scales, 3)`` int64 cells and float64
        fractions (:meth:`anchors`) are given."""
        cells = torch.as_tensor(cells, dtype=torch.int64, device=self.device)
        fractions = torch.as_tensor(fractions, dtype=torch.float64, device=self.device)
        n_scales = self.n_scales
        if cells.ndim != 3 or tuple(cells.shape[1:]) != (n_scales, 3):
            raise ShapeError(f"cells: expected (n, {n_scales}, 3), found {tuple(cells.shape)}")
        if tuple(fractions.shape) != tuple(cells.shape):
            raise ShapeError(
                f"fractions: expected {tuple(cells.shape)}, found {tuple(fractions.shape)}"
            )
        size = self.cube_voxels
        n = cells.shape[0]
        # One spare element: pieces not set are pointed at it.
        flat = torch.zeros(
            n * n_scales * size**3 + 1, dtype=dtype or torch.float32, device=self.device
        )
        if n and self._n_cells:
            for begin in range(0, n, self.query_block):
                stop = min(begin + self.query_block, n)
                self._fill_block(cells[begin:stop], fractions[begin:stop], begin, flat)
        return flat[:-1].view(n, n_scales, size, size, size)

    # -- the kernel -----------------------------------------------------------------------
    def _fill_block(self, cells: Any, splits: Any, offset: int, flat: Any) -> None:
        size = self.cube_voxels
        width = size + 1
        n, n_scales = cells.shape[0], cells.shape[1]
        tables = self._tables
        base = cells - size // 2 + CELL_OFFSET  # (n, S, 3) first cell of each block
        first = (
            ((base[..., 0, None, None] + tables.columns[:, None]) << (2 * CELL_BITS))
            | ((base[..., 1, None, None] + tables.columns[None, :]) << CELL_BITS)
            | base[..., 2, None, None]
        )  # (n, S, W, W): the first cell of each column of each block
        by_scale = first.permute(1, 0, 2, 3).reshape(n_scales, -1)
        lo = torch.searchsorted(self._keys, by_scale)
        hi = torch.searchsorted(self._keys, by_scale + width)
        # Back to query-major order (n, S, W*W), so a run of queries is a run of columns.
        lo = lo.view(n_scales, n, width * width).transpose(0, 1).reshape(-1)
        counts = hi.view(n_scales, n, width * width).transpose(0, 1).reshape(-1) - lo
        per_query = counts.view(n, -1).sum(dim=1)
        columns_per_query = n_scales * width * width
        weights = per_query.cpu().numpy()
        for q0, q1 in _groups(weights, self.pair_budget):
            c0, c1 = q0 * columns_per_query, q1 * columns_per_query
            total = int(weights[q0:q1].sum())
            if total == 0:
                continue
            column = c0 + torch.repeat_interleave(
                torch.arange(c1 - c0, device=self.device), counts[c0:c1], output_size=total
            )
            column_start = torch.cumsum(counts[c0:c1], 0) - counts[c0:c1]
            rank = torch.arange(total, device=self.device) - column_start[column - c0]
            position = lo[column] + rank  # in the scale's key row
            query = torch.div(column, columns_per_query, rounding_mode="floor")
            within = column - query * columns_per_query
            scale = torch.div(within, width * width, rounding_mode="floor")
            within = within - scale * width * width
            ci = torch.div(within, width, rounding_mode="floor")
            cj = within - ci * width
            ck = self._keys[scale, position] - first.reshape(-1)[column]
            cell = self._key_starts[scale] + position
            self._fill_pairs(query, scale, ci, cj, ck, cell, splits, offset, flat)

    def _fill_pairs(
        self,
        query: Any,
        scale: Any,
        ci: Any,
        cj: Any,
        ck: Any,
        cell: Any,
        splits: Any,
        offset: int,
        flat: Any,
    ) -> None:
        tables = self._tables
        wanted = tables.x_parts[ci] & tables.y_parts[cj] & tables.z_parts[ck]
        split = splits[query, scale]  # (P, 3) float64
        filter_row = self._filter_rows[cell]
        filtered = torch.nonzero(filter_row >= 0).view(-1)
        if filtered.numel():
            bounds = self._filters[filter_row[filtered]]  # (F, 14)
            at = split[filtered, None, :]  # (F, 1, 3)
            upper = bounds[:, None, 3:6] >= at  # the piece's upper side: max >= split
            lower = bounds[:, None, 0:3] < at  # its lower side: min < split
            axes = torch.where(tables.code_axes, upper, lower).all(dim=2)  # (F, 8)
            signed = at * tables.code_signs  # exact: multiplications by +-1
            reach = (signed[..., 0] + signed[..., 1]) + signed[..., 2]  # the kernel's order
            possible = _bits(axes & (bounds[:, 6:14] >= reach), tables.bits)
            wanted[filtered] &= possible
        row_start = self._row_starts[cell]
        n_rows = self._row_starts[cell + 1] - row_start
        # Every cell's first rows, then the next rows of the cells still missing a piece.
        begin = _FIRST_ROWS
        found = self._scan_rows(split, row_start, torch.clamp(n_rows, max=begin))
        pending = torch.nonzero(((wanted & ~found) != 0) & (n_rows > begin)).view(-1)
        while pending.numel():  # the next rows of the cells with pieces still unfound
            end = begin * _GROWTH
            length = torch.clamp(n_rows[pending] - begin, max=end - begin)
            found[pending] |= self._scan_rows(split[pending], row_start[pending] + begin, length)
            more = ((wanted[pending] & ~found[pending]) != 0) & (n_rows[pending] > end)
            pending = pending[more]
            begin = end
        self._scatter(query, scale, ci, cj, ck, found & wanted, offset, flat)

    def _scan_rows(self, split: Any, first_row: Any, length: Any) -> Any:
        """Orthant bits (against ``split``) of the rows ``first_row .. first_row + length``
        of each pair, one row visit each (in runs of at most the pair budget)."""
        tables = self._tables
        hit = torch.zeros(first_row.numel() * 8, dtype=torch.bool, device=self.device)
        lengths = length.cpu().numpy()
        for p0, p1 in _groups(lengths, self.pair_budget):
            total = int(lengths[p0:p1].sum())
            if total == 0:
                continue
            owner = p0 + torch.repeat_interleave(
                torch.arange(p1 - p0, device=self.device), length[p0:p1], output_size=total
            )
            start = torch.cumsum(length[p0:p1], 0) - length[p0:p1]
            rows = first_row[owner] + torch.arange(total, device=self.device) - start[owner - p0]
            code = _orthant(self._fractions[rows], split[owner])
            hit[owner * 8 + code] = True
        return _bits(hit.view(-1, 8), tables.bits)

    def _scatter(
        self,
        query: Any,
        scale: Any,
        ci: Any,
        cj: Any,
        ck: Any,
        mask: Any,
        offset: int,
        flat: Any,
    ) -> None:
        """Set the voxel of every piece of ``mask``: piece ``code`` of the cell at layers
        ``(ci, cj, ck)`` of the block is voxel ``(ci, cj, ck) - 1 + code's axis bits``."""
        size = self.cube_voxels
        tables = self._tables
        spare = flat.numel() - 1
        cube = (query + offset) * self.n_scales + scale  # (P,)
        corner = ((cube * size + ci - 1) * size + cj - 1) * size + ck - 1
        index = corner[:, None] + tables.code_offsets  # (P, 8)
        on = tables.mask_codes[mask]  # (P, 8): only pieces inside the cube are in the mask
        flat.index_fill_(0, torch.where(on, index, spare).view(-1), 1)
        flat[spare] = 0


class _Tables:
    """Small constant tables of the kernel, on the device."""

    def __init__(self, size: int, device: Any) -> None:
        self.columns = torch.arange(size + 1, device=device, dtype=torch.int64)
        codes = np.arange(8)
        axes = np.stack([(codes >> a) & 1 for a in range(3)], axis=1).astype(bool)  # (8, 3)
        self.code_axes = torch.as_tensor(axes, device=device)
        self.code_signs = torch.as_tensor(np.where(axes, 1.0, -1.0), device=device)
        self.bits = torch.as_tensor(1 << codes, device=device, dtype=torch.int64)
        self.code_offsets = torch.as_tensor(
            (axes[:, 0] * size + axes[:, 1]) * size + axes[:, 2], device=device
        ).to(torch.int64)  # a piece's voxel from the voxel of piece 0
        masks = np.arange(256)
        self.mask_codes = torch.as_tensor((masks[:, None] >> codes) & 1 == 1, device=device)
        parts = []
        for axis in range(3):
            # Layer c of the block feeds voxel c - 1 with its lower part and voxel c with
            # its upper part: keep the pieces whose voxel lies in 0..C-1.
            table = np.zeros(size + 1, np.int64)
            for layer in range(size + 1):
                for code in range(8):
                    voxel = layer - 1 + ((code >> axis) & 1)
                    if 0 <= voxel < size:
                        table[layer] |= 1 << code
            parts.append(torch.as_tensor(table, device=device))
        self.x_parts, self.y_parts, self.z_parts = parts


def _bits(flags: Any, bits: Any) -> Any:
    """``(P, 8)`` booleans as ``(P,)`` 8-bit masks (no integer matmul: CUDA has none)."""
    return (flags.to(torch.int64) * bits).sum(dim=1)


def _orthant(fractions: Any, split: Any) -> Any:
    """Orthant code of each row against its split: bit ``a`` set where ``t_a >= s_a``."""
    upper = (fractions >= split).to(torch.int64)
    return upper[:, 0] | (upper[:, 1] << 1) | (upper[:, 2] << 2)


def _groups(weights: NDArray[np.int64], budget: int) -> list[tuple[int, int]]:
    """Consecutive runs of items whose weights sum to at most ``budget`` (an item heavier
    than the budget alone)."""
    cumulative = np.cumsum(weights)
    groups = []
    begin, before = 0, 0
    while begin < len(weights):
        end = int(np.searchsorted(cumulative, before + budget, side="right"))
        end = max(end, begin + 1)
        groups.append((begin, end))
        begin, before = end, int(cumulative[end - 1])
    return groups


def _uploader(device: Any) -> Any:
    """Host arrays to ``device``: through pinned memory, without blocking, on CUDA."""
    if device.type != "cuda":
        return lambda array: torch.from_numpy(np.ascontiguousarray(array))
    return lambda array: (
        torch.from_numpy(np.ascontiguousarray(array)).pin_memory().to(device, non_blocking=True)
    )


def pack_cubes(cubes: Any) -> Any:
    """``(n, ...)`` 0/1 cubes as ``(n, ceil(m / 8))`` uint8, the bit order of
    ``numpy.packbits`` (first voxel in the high bit)."""
    n = cubes.shape[0]
    bits = cubes.reshape(n, -1).to(torch.uint8)
    spare = (-bits.shape[1]) % 8
    if spare:
        bits = torch.nn.functional.pad(bits, (0, spare))
    weights = torch.tensor([128, 64, 32, 16, 8, 4, 2, 1], dtype=torch.uint8, device=bits.device)
    return (bits.view(n, -1, 8) * weights).sum(dim=2, dtype=torch.uint8)


def unpack_cubes(packed: Any, shape: tuple[int, ...], *, dtype: Any) -> Any:
    """Inverse of :func:`pack_cubes`: ``(n, *shape)`` cubes of ``dtype``."""
    n = packed.shape[0]
    shifts = torch.arange(7, -1, -1, dtype=torch.uint8, device=packed.device)
    bits = (packed[:, :, None] >> shifts) & 1
    count = int(np.prod(shape))
    return bits.reshape(n, -1)[:, :count].to(dtype).view(n, *shape)
