"""Building the level-of-detail octree of a cache: compiled streaming passes.

Which node a point goes to (see :mod:`~semantic3d.labelling.lod`): walking from the root,
the first node ``n`` on its path where ``rank < capacity / count(n)``, or the leaf.

1. **bounds**: the scan's box and intensity range;
2. **histogram**: the count of every cell of the dense levels (a Morton-ordered grid of
   ``8**dense_depth`` cells, summed up into every coarser level);
3. **refine** (only where cells are over-full, usually one or two passes): each bottom
   cell holding more than ``capacity`` points is refined by a small dense block of deeper
   levels (:class:`_Octree`), counted in a pass over the scan, until no bottom cell is
   over-full; nodes and their breadth-first ids follow from the counts;
4. **counts**: each point's node (a few array reads per depth), counted per node and kept
   in a temporary file (4 bytes a point);
5. **write**: each block sorted by bucket (consecutive nodes of about a block's points)
   and written with one positional write per bucket and column into the staged files,
   then each bucket read back, sorted by node and written over itself
   (:func:`_write_columns`).

Blocks are read from the cache's column files with plain reads into reused buffers (never
through memory maps, whose touched pages would count as the process's memory), so memory
is the dense levels (``~8**dense_depth * 9.1`` bytes: 153 MB at depth 8), the refining
blocks (at most :data:`REFINE_CELLS` cells, 8 bytes each, a pass) plus one block and one
bucket, whatever the scan's size; the temporary files take 8 bytes a point of disk while
it runs. Throughput is in ``benchmarks/bench_labelling.py``.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from semantic3d.io.cache import open_cache
from semantic3d.labelling import _lod_kernels as kernels

__all__ = [
    "BUILD_BLOCK_POINTS",
    "DENSE_DEPTH_LIMIT",
    "MAX_NODE_DEPTH",
    "POSITION_DEPTH",
    "build_lod_files",
]

logger = logging.getLogger(__name__)

BUILD_BLOCK_POINTS = 1 << 21
DENSE_DEPTH_LIMIT = 8
"""Deepest level of the dense histogram (``8**8`` cells)."""
POSITION_DEPTH = 24
"""Depth from which cells split by a hash of the points' scan positions, not by space
(cells of ``cube / 2**24``: 50 µm for a 800 m scan, below the float32 copy's resolution
there): the points of a smaller over-full cell (duplicates) are still spread over nodes."""
MAX_NODE_DEPTH = POSITION_DEPTH + 21
"""The deepest node (21 levels of 3 hash bits each below :data:`POSITION_DEPTH`)."""
BLOCK_LEVELS_LIMIT = 7
"""Levels of one refining block at most (``8**7`` bottom cells)."""
REFINE_CELLS = 1 << 22
"""Cells the refining blocks added by one pass hold at most (two 4-byte arrays each)."""


class _ColumnBlocks:
    """Blocks of a cache's columns read into reused buffers (plain reads, no memory maps)."""

    def __init__(self, cache: Path, block_points: int) -> None:
        scan = open_cache(cache)
        self.n_points = scan.n_points
        self.block_points = block_points
        self._columns: dict[str, tuple[Path, int, NDArray[Any]]] = {}
        for name, column in (("xyz", scan.xyz), ("intensity", scan.intensity), ("rgb", scan.rgb)):
            offset = int(column.offset) if isinstance(column, np.memmap) else 128
            shape = (block_points, *column.shape[1:])
            self._columns[name] = (cache / f"{name}.npy", offset, np.empty(shape, column.dtype))
        del scan

    def iter(self, names: tuple[str, ...]) -> Iterator[tuple[int, dict[str, NDArray[Any]]]]:
        """``(first index, {name: block view})`` over the scan, the same buffers each time."""
        streams = {name: self._columns[name][0].open("rb", buffering=0) for name in names}
        try:
            for start in range(0, self.n_points, self.block_points):
                n = min(self.block_points, self.n_points - start)
                blocks = {}
                for name, stream in streams.items():
                    _, offset, buffer = self._columns[name]
                    row = buffer.itemsize * int(np.prod(buffer.shape[1:], dtype=np.int64))
                    view = buffer[:n]
                    stream.seek(offset + start * row)
                    target = memoryview(view.reshape(-1).view(np.uint8))  # type: ignore[arg-type]
                    got = 0
                    while got < n * row:
                        read = stream.readinto(target[got:])
                        if not read:
                            raise OSError(f"{self._columns[name][0]}: unexpected end of file")
                        got += read
                    blocks[name] = view
                yield start, blocks
        finally:
            for stream in streams.values():
                stream.close()


def _dense_levels(
    leaf_counts: NDArray[np.uint32], depth: int
) -> tuple[NDArray[np.uint32], NDArray[np.int64]]:
    """Counts of every dense level, flattened (leaves summed up); the level offsets."""
    offsets = np.array([kernels.level_offset(d) for d in range(depth + 2)], np.int64)
    counts = np.zeros(int(offsets[-1]), np.uint32)
    counts[offsets[depth] : offsets[depth + 1]] = leaf_counts
    for d in range(depth - 1, -1, -1):
        finer = counts[offsets[d + 1] : offsets[d + 2]].reshape(-1, 8)
        counts[offsets[d] : offsets[d + 1]] = finer.sum(axis=1, dtype=np.uint64)
    return counts, offsets


def _deinterleave(keys: NDArray[np.int64], depth: int) -> NDArray[np.int64]:
    cells = np.zeros((keys.size, 3), np.int64)
    for bit in range(depth):
        for axis in range(3):
            cells[:, axis] |= ((keys >> (3 * bit + 2 - axis)) & 1) << bit
    return cells


def _refined_levels(count: int, capacity: int, depth: int) -> int:
    """Levels of the block refining a cell of ``count`` points at ``depth``.

    Above :data:`POSITION_DEPTH` the cells split space: the points of a scan lie on
    surfaces, so 4 cells a level is the rate assumed, with one level to spare; below it
    they split by a hash (8 a level, one to spare).
    """
    ratio = count / capacity
    if depth < POSITION_DEPTH:
        wanted = int(np.ceil(np.log(ratio) / np.log(4.0))) + 1
        return max(1, min(wanted, BLOCK_LEVELS_LIMIT, POSITION_DEPTH - depth))
    wanted = int(np.ceil(np.log(ratio) / np.log(8.0))) + 1
    return max(1, min(wanted, BLOCK_LEVELS_LIMIT, MAX_NODE_DEPTH - depth))


class _Octree:
    """The octree's cell counts: the dense levels (block 0) and the blocks refining cells.

    A block holds the dense levels ``1..levels`` below its root cell (level 0, the root,
    too for block 0). A bottom cell of a block holding more than ``capacity`` points is
    refined by a new block (``ids[cell] = -2 - block``) in a further pass over the scan,
    until no bottom cell is over-full (or the deepest level is reached). A new block
    starts at the deepest cell holding every point of the refined cell when its parent
    block's points all lie in that cell (known from the points' box), so a tiny dense
    cluster does not take a pass per few levels.
    """

    def __init__(self, leaf_counts: NDArray[np.uint32], dense_depth: int, capacity: int) -> None:
        self.capacity = capacity
        self.dense_counts, self.dense_offsets = _dense_levels(leaf_counts, dense_depth)
        self.dense_ids = np.full(self.dense_counts.size, -1, np.int32)
        self.counts = np.zeros(0, np.uint32)
        self.ids = np.zeros(0, np.int32)
        self.offset = [0]
        self.depth = [0]
        self.levels = [dense_depth]
        self.cell: list[tuple[int, int, int]] = [(0, 0, 0)]
        self.total = [int(self.dense_counts[0])]
        self.parent_depth = [-1]
        self.boxes: list[NDArray[np.int64] | None] = [None]
        self.examine_from = 0  # the blocks whose bottom cells were counted last
        self.first_new = 1  # the blocks the next pass counts
        self.block_node = np.zeros(0, np.int64)  # the node of the cell each block refines

    @property
    def n_blocks(self) -> int:
        return len(self.offset)

    def arrays(self) -> tuple[NDArray[np.int64], ...]:
        """Block offsets, root depths, levels and root cells, for the kernels."""
        return (
            np.asarray(self.offset, np.int64),
            np.asarray(self.depth, np.int64),
            np.asarray(self.levels, np.int64),
            np.asarray(self.cell, np.int64).reshape(-1, 3),
        )

    def _bottom(self, block: int) -> tuple[NDArray[np.uint32], NDArray[np.int32], int]:
        levels = self.levels[block]
        start = self.offset[block] + kernels.level_offset(levels)
        stop = self.offset[block] + kernels.level_offset(levels + 1)
        counts, ids = (self.dense_counts, self.dense_ids) if block == 0 else (self.counts, self.ids)
        return counts[start:stop], ids[start:stop], start

    def refine(self) -> bool:
        """Add a block under every over-full bottom cell of the last blocks; any added.

        A block has levels enough for its cell's points to fall under the capacity
        (:func:`_refined_levels`), fewer when the blocks of this pass would exceed
        :data:`REFINE_CELLS` cells (the next pass refines further).
        """
        wanted: list[tuple[int, int, int, int, tuple[int, int, int]]] = []
        for block in range(self.examine_from, self.n_blocks):
            depth = self.depth[block] + self.levels[block]
            if depth >= MAX_NODE_DEPTH:
                continue
            bottom, _, start = self._bottom(block)
            keys = np.flatnonzero(bottom > self.capacity)
            if self.depth[block] < POSITION_DEPTH:
                base = np.asarray(self.cell[block], np.int64) << self.levels[block]
                cells = base | _deinterleave(keys.astype(np.int64), self.levels[block])
            else:
                cells = np.tile(np.asarray(self.cell[block], np.int64), (keys.size, 1))
            for key, cell in zip(keys.tolist(), cells.tolist(), strict=True):
                count = int(bottom[key])
                root, cell = depth, tuple(cell)
                box = self.boxes[block]
                if depth < POSITION_DEPTH and count == self.total[block] and box is not None:
                    spread = int(np.bitwise_or.reduce(box[:3] ^ box[3:]))
                    root = max(depth, POSITION_DEPTH - spread.bit_length())
                    cell = tuple((box[:3] >> (POSITION_DEPTH - root)).tolist())
                wanted.append((block, start + key, count, root, cell))
        self.examine_from = self.first_new = self.n_blocks
        if not wanted:
            return False
        levels = [_refined_levels(count, self.capacity, root) for _, _, count, root, _ in wanted]
        while sum(kernels.level_offset(k + 1) for k in levels) > REFINE_CELLS and max(levels) > 1:
            top = max(levels)
            levels = [k - 1 if k == top else k for k in levels]
        size = self.counts.size
        for (block, at, count, root, cell), k in zip(wanted, levels, strict=True):
            (self.dense_ids if block == 0 else self.ids)[at] = -2 - self.n_blocks
            self.offset.append(size)
            self.depth.append(root)
            self.levels.append(k)
            self.cell.append(cell)
            self.total.append(count)
            self.parent_depth.append(self.depth[block] + self.levels[block])
            self.boxes.append(None)
            size += kernels.level_offset(k + 1)
        grown = size - self.counts.size
        self.counts = np.concatenate([self.counts, np.zeros(grown, np.uint32)])
        self.ids = np.concatenate([self.ids, np.full(grown, -1, np.int32)])
        return True

    def count_pass(self, columns: _ColumnBlocks, geometry: _Grid, report: _Report) -> None:
        """Count the points of the new blocks' bottom cells (one pass over the scan)."""
        offset, depth, levels, cell = self.arrays()
        boxes = np.empty((self.n_blocks, 6), np.int64)
        boxes[:, :3] = np.iinfo(np.int64).max
        boxes[:, 3:] = -1
        for start, chunk in columns.iter(("xyz",)):
            kernels.refine_histogram(
                chunk["xyz"], start, geometry.cube_min, geometry.scales, kernels._SPREAD,
                POSITION_DEPTH, self.dense_counts, self.dense_ids, self.counts, self.ids,
                offset, depth, levels, cell, self.first_new, boxes,
            )  # fmt: skip
            report("refine", start, len(chunk["xyz"]))
        for block in range(self.first_new, self.n_blocks):
            kernels.sum_levels(self.counts, self.offset[block], self.levels[block])
            if int(self.counts[self.offset[block]]) != self.total[block]:
                raise RuntimeError(
                    f"level-of-detail refinement: block {block} expected {self.total[block]} "
                    f"points, found {int(self.counts[self.offset[block]])}"
                )
            if self.depth[block] < POSITION_DEPTH:
                self.boxes[block] = boxes[block].copy()

    def nodes(self, geometry: _Grid) -> _Nodes:
        """Every node, with breadth-first ids (depth, then Morton order) written into the
        cells' ids (a refined bottom cell's id goes to ``block_node`` instead)."""
        capacity = self.capacity
        depth_of: list[NDArray[np.int64]] = []
        parent_of: list[NDArray[np.int64]] = []
        child_of: list[NDArray[np.int64]] = []
        low_of: list[NDArray[np.float64]] = []
        edge_of: list[NDArray[np.float64]] = []
        ref_block: list[NDArray[np.int64]] = []
        ref_at: list[NDArray[np.int64]] = []
        block_node = np.full(self.n_blocks, -1, np.int64)  # provisional ids first
        n = 0

        def add(depth: int, parents: NDArray[np.int64], keys: NDArray[np.int64],
                lows: NDArray[np.float64], edge: float, block: int,
                at: NDArray[np.int64]) -> NDArray[np.int64]:  # fmt: skip
            nonlocal n
            ids = np.arange(n, n + keys.size, dtype=np.int64)
            n += keys.size
            depth_of.append(np.full(keys.size, depth, np.int64))
            parent_of.append(parents.astype(np.int64))
            child_of.append(keys & 7)
            low_of.append(lows.reshape(-1, 3))
            edge_of.append(np.full(keys.size, edge))
            ref_block.append(np.full(keys.size, block, np.int64))
            ref_at.append(at.astype(np.int64))
            return ids

        # The dense levels: nodes are the cells holding points whose parent is over-full.
        # Their ids are final (every node below them is deeper): written into the cells.
        offsets, counts, dense_ids = self.dense_offsets, self.dense_counts, self.dense_ids
        bottom = slice(int(offsets[-2]), int(offsets[-1]))
        refined = np.flatnonzero(dense_ids[bottom] <= -2)
        refined_blocks = -2 - dense_ids[bottom][refined].astype(np.int64)
        for d in range(self.levels[0] + 1):
            level_counts = counts[offsets[d] : offsets[d + 1]]
            if d == 0:
                keys = np.flatnonzero(level_counts > 0)
                parents = np.full(keys.size, -1, np.int64)
            else:
                internal = counts[offsets[d - 1] : offsets[d]] > capacity
                keys = np.flatnonzero((level_counts > 0) & np.repeat(internal, 8))
                parents = dense_ids[offsets[d - 1] + (keys >> 3)].astype(np.int64)
            edge = geometry.cube_size / (1 << d)
            lows = geometry.local_min + edge * _deinterleave(keys, d).astype(np.float64)
            ids = add(d, parents, keys, lows, edge, -1, keys)
            dense_ids[offsets[d] + keys] = ids
        block_node[refined_blocks] = dense_ids[bottom][refined]
        dense_ids[bottom][refined] = (-2 - refined_blocks).astype(np.int32)
        n_dense = n

        for block in range(1, self.n_blocks):
            root, levels, base = self.depth[block], self.levels[block], self.offset[block]
            cell = np.asarray(self.cell[block], np.int64)
            parent = np.array([block_node[block]], np.int64)
            for d in range(self.parent_depth[block] + 1, root + 1):  # a chain of one-child cells
                at = cell >> (root - d)
                key = np.array([int(at[0] & 1) << 2 | int(at[1] & 1) << 1 | int(at[2] & 1)])
                edge = geometry.cube_size / (1 << d)
                parent = add(d, parent, key, geometry.local_min + edge * at, edge, -1, key)
            previous = np.zeros(1, np.int64) + parent[0]
            counts = self.counts
            for level in range(1, levels + 1):
                start = base + kernels.level_offset(level)
                above = base + kernels.level_offset(level - 1)
                level_counts = counts[start : base + kernels.level_offset(level + 1)]
                internal = counts[above:start] > capacity
                keys = np.flatnonzero((level_counts > 0) & np.repeat(internal, 8))
                d = root + level
                if root < POSITION_DEPTH:
                    edge = geometry.cube_size / (1 << d)
                    at = (cell << level) | _deinterleave(keys, level)
                else:
                    edge = geometry.cube_size / (1 << POSITION_DEPTH)
                    at = np.tile(cell, (keys.size, 1))
                lows = geometry.local_min + edge * at.astype(np.float64)
                ids = add(d, previous[keys >> 3], keys, lows, edge, block, start + keys)
                previous = np.full(level_counts.size, -1, np.int64)
                previous[keys] = ids
            bottom_ids = self.ids[
                base + kernels.level_offset(levels) : base + kernels.level_offset(levels + 1)
            ]
            refined = np.flatnonzero(bottom_ids <= -2)
            block_node[-2 - bottom_ids[refined].astype(np.int64)] = previous[refined]

        depth = np.concatenate(depth_of) if depth_of else np.zeros(0, np.int64)
        parent = np.concatenate(parent_of) if parent_of else np.zeros(0, np.int64)
        child = np.concatenate(child_of) if child_of else np.zeros(0, np.int64)
        # Breadth first: by depth, then by the parent's id, then by the child's octant.
        final = np.empty(n, np.int64)
        next_id = 0
        for d in range(int(depth.max()) + 1 if n else 0):
            here = np.flatnonzero(depth == d)
            key = child[here] if d == 0 else final[parent[here]] * 8 + child[here]
            here = here[np.argsort(key, kind="stable")]
            final[here] = np.arange(next_id, next_id + here.size)
            next_id += here.size
        if not np.array_equal(final[:n_dense], np.arange(n_dense)):
            raise RuntimeError("level-of-detail build: the dense levels' ids are not first")
        blocks = np.concatenate(ref_block) if ref_block else np.zeros(0, np.int64)
        at = (np.concatenate(ref_at) if ref_at else np.zeros(0, np.int64))[blocks > 0]
        plain = self.ids[at] > -2  # a refined bottom cell's id is its block's
        self.ids[at[plain]] = final[blocks > 0][plain]
        self.block_node = np.full(self.n_blocks, -1, np.int64)
        self.block_node[block_node >= 0] = final[block_node[block_node >= 0]]
        order = np.argsort(final)
        return _Nodes(
            depth=depth[order],
            parent=np.where(parent[order] >= 0, final[np.maximum(parent[order], 0)], -1),
            child=child[order],
            low=(np.concatenate(low_of) if low_of else np.zeros((0, 3)))[order],
            edge=(np.concatenate(edge_of) if edge_of else np.zeros(0))[order],
        )


@dataclass(frozen=True, slots=True)
class _Grid:
    """The octree's cube: its corner (scan frame and re-centred) and edge, scales per depth."""

    cube_min: NDArray[np.float64]
    local_min: NDArray[np.float64]
    cube_size: float
    scales: NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class _Nodes:
    """Every node in id order: depth, parent id (-1 for the root), octant, cube corner, edge."""

    depth: NDArray[np.int64]
    parent: NDArray[np.int64]
    child: NDArray[np.int64]
    low: NDArray[np.float64]
    edge: NDArray[np.float64]


_Report = Callable[[str, int, int], None]


def _manifest_nodes(
    nodes: _Nodes, starts: NDArray[np.int64], sizes: NDArray[np.int64]
) -> list[dict[str, Any]]:
    """The manifest entries of every node, in id order (breadth first, Morton order)."""
    result: list[dict[str, Any]] = []
    names: list[str] = []
    columns = (nodes.depth, nodes.parent, nodes.child, nodes.low, nodes.edge)
    for node_id, (depth, parent, child, low, edge) in enumerate(
        zip(*(column.tolist() for column in columns), strict=True)
    ):
        name = "r" if parent < 0 else names[parent] + str(child)
        names.append(name)
        result.append(
            {
                "id": node_id,
                "name": name,
                "depth": depth,
                "bounds": [*low, *(np.asarray(low) + edge).tolist()],
                "start": int(starts[node_id]),
                "count": int(sizes[node_id]),
                "children": [],
            }
        )
        if parent >= 0:
            result[parent]["children"].append(node_id)
    return result


def _open_column(path: Path, dtype: np.dtype[Any], shape: tuple[int, ...]) -> tuple[int, int, int]:
    """Create a ``.npy`` file of ``shape``; return its descriptor, data offset and row size."""
    array = np.lib.format.open_memmap(path, mode="w+", dtype=dtype, shape=shape)
    offset = int(array.offset)
    del array
    row_bytes = dtype.itemsize * (shape[1] if len(shape) > 1 else 1)
    return os.open(path, os.O_RDWR), offset, row_bytes


def _write_all(stream: Any, array: NDArray[Any]) -> None:
    """Write a contiguous array's bytes to an unbuffered stream."""
    view = memoryview(array.reshape(-1).view(np.uint8))  # type: ignore[arg-type]
    done = 0
    while done < len(view):
        done += stream.write(view[done:])


def _pwrite_all(fd: int, array: NDArray[Any], offset: int) -> None:
    view = memoryview(array.reshape(-1).view(np.uint8))  # type: ignore[arg-type]
    done = 0
    while done < len(view):
        done += os.pwrite(fd, view[done:], offset + done)


def _pread_all(fd: int, array: NDArray[Any], offset: int) -> None:
    view = memoryview(array.reshape(-1).view(np.uint8))  # type: ignore[arg-type]
    done = 0
    while done < len(view):
        read = os.preadv(fd, [view[done:]], offset + done)
        if not read:
            raise OSError(f"unexpected end of a level-of-detail file at byte {offset + done}")
        done += read


def _buckets(sizes: NDArray[np.int64], bucket_points: int) -> NDArray[np.int32]:
    """Each node's bucket: consecutive nodes holding at most ``bucket_points`` together
    (or one larger node)."""
    bucket_of = np.empty(sizes.size, np.int32)
    bucket, held = -1, bucket_points
    for node, size in enumerate(sizes.tolist()):
        if held + size > bucket_points and held > 0:
            bucket, held = bucket + 1, 0
        bucket_of[node] = bucket
        held += size
    return bucket_of


def _write_columns(
    staging: Path,
    columns: _ColumnBlocks,
    node_file: Path,
    bucketed_file: Path,
    sizes: NDArray[np.int64],
    starts: NDArray[np.int64],
    origin: NDArray[np.float64],
    i_range: NDArray[np.int64],
    report: _Report,
) -> None:
    """Write the node-ordered columns: two passes of few, large writes.

    Pass 5 sorts each block by bucket (consecutive nodes of about a block's points) and
    writes each bucket's run at its place in the columns (in scan order); then each bucket
    is read back, sorted by node (stably: each node's points stay in scan order) and
    written over itself. One write per node and block instead would be tens of thousands
    of small writes a block when the nodes are many (10**4 at 10**8 points).
    """
    n_points, block_points = columns.n_points, columns.block_points
    n_nodes = int(sizes.size)
    bucket_points = max(block_points, int(sizes.max()) if n_nodes else 0)
    bucket_of = _buckets(sizes, block_points)
    n_buckets = int(bucket_of[-1]) + 1 if n_nodes else 0
    first_node = np.searchsorted(bucket_of, np.arange(n_buckets + 1)).astype(np.int64)
    bucket_start = np.append(starts, n_points)[first_node]
    specs: dict[str, tuple[np.dtype[Any], tuple[int, ...]]] = {
        "positions": (np.dtype(np.float32), (3,)),
        "rgb": (np.dtype(np.uint8), (3,)),
        "intensity": (np.dtype(np.uint8), ()),
        "index": (np.dtype(np.uint32), ()),
        "node": (np.dtype(np.int32), ()),
    }
    files = {
        name: _open_column(staging / f"{name}.npy", dtype, (n_points, *tail))
        for name, (dtype, tail) in specs.items()
        if name != "node"
    }
    bucketed = os.open(bucketed_file, os.O_RDWR | os.O_CREAT | os.O_TRUNC, 0o600)
    files["node"] = (bucketed, 0, 4)
    buffers = {
        name: np.empty((bucket_points, *tail), dtype) for name, (dtype, tail) in specs.items()
    }
    present = np.empty(max(n_buckets, 1), np.int64)
    run_start = np.empty(max(n_buckets, 1), np.int64)
    run_count = np.empty(max(n_buckets, 1), np.int64)
    fill = bucket_start[:-1].copy()
    i_low = float(i_range[0])
    i_scale = 255.0 / max(float(i_range[1] - i_range[0]), 1.0)
    node_of = np.empty(block_points, np.int32)
    try:
        # Pass 5: every block sorted by bucket, one positional write per bucket and column.
        with node_file.open("rb", buffering=0) as nodes:
            for start, block in columns.iter(("xyz", "rgb", "intensity")):
                n = len(block["xyz"])
                _pread_all(nodes.fileno(), node_of[:n], start * 4)
                m = kernels.group_block(
                    node_of[:n], bucket_of, n_buckets, start, block["xyz"], origin,
                    block["rgb"], block["intensity"], i_low, i_scale, buffers["positions"],
                    buffers["rgb"], buffers["intensity"], buffers["index"], buffers["node"],
                    present, run_start, run_count,
                )  # fmt: skip
                for bucket, a, count in zip(
                    present[:m].tolist(), run_start[:m].tolist(), run_count[:m].tolist(),
                    strict=True,
                ):  # fmt: skip
                    at = int(fill[bucket])
                    for name, (fd, offset, row_bytes) in files.items():
                        _pwrite_all(fd, buffers[name][a : a + count], offset + at * row_bytes)
                    fill[bucket] += count
                report("write", start, n)
        # Each bucket of several nodes sorted by node, in place.
        sorted_buffers = {
            name: np.empty((bucket_points, *tail), dtype)
            for name, (dtype, tail) in specs.items()
            if name != "node"
        }
        for bucket in range(n_buckets):
            first, last = int(first_node[bucket]), int(first_node[bucket + 1])
            at, count = (
                int(bucket_start[bucket]),
                int(bucket_start[bucket + 1] - bucket_start[bucket]),
            )
            if last - first < 2 or count == 0:
                continue
            for name, (fd, offset, row_bytes) in files.items():
                _pread_all(fd, buffers[name][:count], offset + at * row_bytes)
            kernels.sort_bucket(
                buffers["node"][:count], first, last - first, buffers["positions"][:count],
                buffers["rgb"][:count], buffers["intensity"][:count], buffers["index"][:count],
                sorted_buffers["positions"], sorted_buffers["rgb"], sorted_buffers["intensity"],
                sorted_buffers["index"],
            )  # fmt: skip
            for name, (fd, offset, row_bytes) in files.items():
                if name != "node":
                    _pwrite_all(fd, sorted_buffers[name][:count], offset + at * row_bytes)
    finally:
        for fd, _, _ in files.values():
            os.close(fd)


def build_lod_files(
    cache: Path,
    staging: Path,
    *,
    capacity: int,
    dense_depth: int,
    fingerprint: str,
    version: int,
    block_points: int = BUILD_BLOCK_POINTS,
    progress: Callable[[str, int, int], None] | None = None,
) -> int:
    """Write the level-of-detail files of ``cache`` into the folder ``staging``; node count."""
    if not 0 <= dense_depth <= DENSE_DEPTH_LIMIT:
        raise ValueError(f"dense_depth: expected 0..{DENSE_DEPTH_LIMIT}, found {dense_depth}")
    columns = _ColumnBlocks(cache, block_points)
    n_points = columns.n_points
    if n_points >= 2**32 - 1:
        raise ValueError(f"n_points: expected fewer than 2**32 points, found {n_points}")

    def report(stage: str, start: int, n: int) -> None:
        if progress is not None:
            progress(stage, start + n, n_points)

    # Pass 1: bounds and intensity range.
    low = np.full(3, np.inf)
    high = np.full(3, -np.inf)
    i_range = np.array([np.iinfo(np.int64).max, np.iinfo(np.int64).min], np.int64)
    for start, block in columns.iter(("xyz", "intensity")):
        kernels.bounds(block["xyz"], block["intensity"], low, high, i_range)
        report("bounds", start, len(block["xyz"]))
    if n_points == 0:
        low = high = np.zeros(3)
        i_range[:] = 0
    origin = np.round((low + high) / 2.0)
    cube_size = float(max((high - low).max(), 1e-3)) * (1 + 1e-9)
    cube_min = low.astype(np.float64)
    depth = dense_depth
    top = (1 << depth) - 1
    scale = float(1 << depth) / cube_size
    spread = kernels._SPREAD

    # Pass 2: leaf cell counts of the dense levels, summed up into every level.
    leaf_counts = np.zeros(1 << (3 * depth), np.uint32)
    for start, block in columns.iter(("xyz",)):
        kernels.histogram(block["xyz"], cube_min, scale, top, spread, leaf_counts)
        report("histogram", start, len(block["xyz"]))
    octree = _Octree(leaf_counts, depth, capacity)
    del leaf_counts

    # Further passes while cells hold more than ``capacity`` points: blocks of deeper levels.
    grid = _Grid(
        cube_min=cube_min,
        local_min=cube_min - origin,
        cube_size=cube_size,
        scales=np.array([float(1 << d) / cube_size for d in range(POSITION_DEPTH + 1)]),
    )
    while octree.refine():
        octree.count_pass(columns, grid, report)
    nodes = octree.nodes(grid)
    n_nodes = len(nodes.depth)
    block_offset, block_depth, block_levels, block_cell = octree.arrays()

    def assign(start: int, xyz: NDArray[np.float64], out: NDArray[np.int32]) -> None:
        kernels.assign(
            xyz, start, cube_min, grid.scales, spread, POSITION_DEPTH, octree.dense_counts,
            octree.dense_ids, octree.counts, octree.ids, block_offset, block_depth,
            block_levels, block_cell, octree.block_node, capacity, out,
        )  # fmt: skip

    # Pass 4: each point's node (kept in a temporary file), points per node.
    node_of = np.empty(block_points, np.int32)
    sizes = np.zeros(max(n_nodes, 1), np.int64)
    node_file = staging / "node.tmp"
    bucketed_file = staging / "node-bucketed.tmp"
    try:
        with node_file.open("wb", buffering=0) as stream:
            for start, block in columns.iter(("xyz",)):
                n = len(block["xyz"])
                assign(start, block["xyz"], node_of[:n])
                kernels.count_nodes(node_of[:n], sizes)
                _write_all(stream, node_of[:n])
                report("counts", start, n)
        starts = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
        _write_columns(
            staging, columns, node_file, bucketed_file, sizes, starts, origin, i_range, report
        )
    finally:
        node_file.unlink(missing_ok=True)
        bucketed_file.unlink(missing_ok=True)
    manifest = {
        "version": version,
        "source": fingerprint,
        "n_points": n_points,
        "origin": origin.tolist(),
        "cube_min": cube_min.tolist(),
        "cube_size": cube_size,
        "dense_depth": depth,
        "position_depth": POSITION_DEPTH,
        "max_depth": int(nodes.depth.max()) if n_nodes else 0,
        "capacity": capacity,
        "bounds_min": low.tolist(),
        "bounds_max": high.tolist(),
        "intensity_range": [float(i_range[0]), float(i_range[1])],
        "nodes": _manifest_nodes(nodes, starts, sizes),
    }
    (staging / "lod.json").write_text(json.dumps(manifest) + "\n", encoding="utf-8")
    return n_nodes


def replace_folder(staging: Path, destination: Path) -> None:
    """Rename ``staging`` to ``destination``, retiring an older folder there."""
    if destination.exists():
        retired = destination.parent / f".{destination.name}.old-{uuid.uuid4().hex[:12]}"
        destination.rename(retired)
        staging.rename(destination)
        shutil.rmtree(retired, ignore_errors=True)
    else:
        staging.rename(destination)
