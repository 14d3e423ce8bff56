"""Building the level-of-detail octree of a cache: four compiled streaming passes.

Which node a point goes to (see :mod:`~semantic3d.labelling.lod`): walking from the root,
the first node ``n`` on its path where ``rank < capacity / count(n)``, or the leaf.

1. **bounds**: the scan's box and intensity range;
2. **histogram**: the count of every leaf cell (a dense Morton-ordered grid of
   ``8**max_depth`` cells), summed up into every coarser level; nodes and their
   breadth-first ids follow from the counts;
3. **sizes**: each point's node (a few array reads per depth), counted per node;
4. **write**: each block sorted by node (a counting sort) and written with one positional
   write per node and column into the staged files.

Blocks are read from the cache's column files with plain reads into reused buffers (never
through memory maps, whose touched pages would count as the process's memory), so memory
is the dense levels (``~8**max_depth * 9.1`` bytes: 153 MB at depth 8) plus one block,
whatever the scan's size. Throughput is in ``benchmarks/bench_labelling.py``.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from semantic3d.io.cache import open_cache
from semantic3d.labelling import _lod_kernels as kernels

__all__ = ["BUILD_BLOCK_POINTS", "MAX_DEPTH_LIMIT", "build_lod_files"]

logger = logging.getLogger(__name__)

BUILD_BLOCK_POINTS = 1 << 21
MAX_DEPTH_LIMIT = 8
"""Deepest octree level the dense build supports (``8**8`` leaf cells)."""


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


def _levels(
    leaf_counts: NDArray[np.uint32], depth: int, capacity: int
) -> tuple[NDArray[np.uint32], NDArray[np.int32], NDArray[np.int64], int]:
    """Counts and node ids of every level, flattened; the level offsets and node count."""
    offsets = np.array([kernels.level_offset(d) for d in range(depth + 2)], np.int64)
    counts = np.zeros(int(offsets[-1]), np.uint32)
    counts[offsets[depth] : offsets[depth + 1]] = leaf_counts
    for d in range(depth - 1, -1, -1):
        finer = counts[offsets[d + 1] : offsets[d + 2]].reshape(-1, 8)
        counts[offsets[d] : offsets[d + 1]] = finer.sum(axis=1, dtype=np.uint64)
    ids = np.full(counts.size, -1, np.int32)
    next_id = 0
    for d in range(depth + 1):
        level = counts[offsets[d] : offsets[d + 1]]
        if d == 0:
            is_node = level > 0
        else:
            parent = counts[offsets[d - 1] : offsets[d]]
            internal = parent > capacity
            is_node = (level > 0) & np.repeat(internal, 8)
        where = np.flatnonzero(is_node)
        ids[offsets[d] + where] = np.arange(next_id, next_id + where.size, dtype=np.int32)
        next_id += where.size
    return counts, ids, offsets, next_id


def _deinterleave(keys: NDArray[np.int64], depth: int) -> NDArray[np.int64]:
    cells = np.zeros((keys.size, 3), np.int64)
    for bit in range(depth):
        for axis in range(3):
            cells[:, axis] |= ((keys >> (3 * bit + 2 - axis)) & 1) << bit
    return cells


def _manifest_nodes(
    counts: NDArray[np.uint32],
    ids: NDArray[np.int32],
    offsets: NDArray[np.int64],
    depth: int,
    starts: NDArray[np.int64],
    sizes: NDArray[np.int64],
    cube_min: NDArray[np.float64],
    cube_size: float,
) -> list[dict[str, Any]]:
    """The manifest entries of every node, in id order (breadth first, Morton order)."""
    result: list[dict[str, Any]] = []
    names: list[str] = []
    for d in range(depth + 1):
        level_ids = ids[offsets[d] : offsets[d + 1]]
        keys = np.flatnonzero(level_ids >= 0)
        if keys.size == 0:
            continue
        edge = cube_size / (1 << d)
        lows = cube_min + edge * _deinterleave(keys, d).astype(np.float64)
        parents = ids[offsets[d - 1] + (keys >> 3)] if d > 0 else np.full(keys.size, -1, np.int32)
        for key, node_id, parent, low in zip(
            keys.tolist(), level_ids[keys].tolist(), parents.tolist(), lows.tolist(), strict=True
        ):
            name = "r" if parent < 0 else names[parent] + str(key & 7)
            names.append(name)
            result.append(
                {
                    "id": node_id,
                    "name": name,
                    "depth": d,
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
    return os.open(path, os.O_WRONLY), offset, row_bytes


def build_lod_files(
    cache: Path,
    staging: Path,
    *,
    capacity: int,
    max_depth: int,
    fingerprint: str,
    version: int,
    block_points: int = BUILD_BLOCK_POINTS,
    progress: Callable[[str, int, int], None] | None = None,
) -> int:
    """Write the level-of-detail files of ``cache`` into the folder ``staging``; node count."""
    if not 0 <= max_depth <= MAX_DEPTH_LIMIT:
        raise ValueError(f"max_depth: expected 0..{MAX_DEPTH_LIMIT}, found {max_depth}")
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
    depth = max_depth
    top = (1 << depth) - 1
    scale = float(1 << depth) / cube_size
    spread = kernels._SPREAD

    # Pass 2: leaf cell counts, then every level, the nodes and their ids.
    leaf_counts = np.zeros(1 << (3 * depth), np.uint32)
    for start, block in columns.iter(("xyz",)):
        kernels.histogram(block["xyz"], cube_min, scale, top, spread, leaf_counts)
        report("histogram", start, len(block["xyz"]))
    counts, ids, offsets, n_nodes = _levels(leaf_counts, depth, capacity)
    del leaf_counts

    # Pass 3: points per node.
    node_of = np.empty(block_points, np.int32)
    sizes = np.zeros(max(n_nodes, 1), np.int64)
    for start, block in columns.iter(("xyz",)):
        n = len(block["xyz"])
        kernels.assign(
            block["xyz"], start, cube_min, scale, top, spread, depth, counts, ids, offsets,
            capacity, node_of[:n],
        )  # fmt: skip
        kernels.count_nodes(node_of[:n], sizes)
        report("counts", start, n)
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)

    # Pass 4: every block sorted by node, one positional write per node and column.
    index_dtype = np.dtype(np.uint32)
    specs: dict[str, tuple[np.dtype[Any], tuple[int, ...]]] = {
        "positions": (np.dtype(np.float32), (n_points, 3)),
        "rgb": (np.dtype(np.uint8), (n_points, 3)),
        "intensity": (np.dtype(np.uint8), (n_points,)),
        "index": (index_dtype, (n_points,)),
    }
    files = {name: _open_column(staging / f"{name}.npy", *spec) for name, spec in specs.items()}
    buffers: dict[str, NDArray[Any]] = {
        "positions": np.empty((block_points, 3), np.float32),
        "rgb": np.empty((block_points, 3), np.uint8),
        "intensity": np.empty(block_points, np.uint8),
        "index": np.empty(block_points, index_dtype),
    }
    present = np.empty(max(n_nodes, 1), np.int64)
    run_start = np.empty(max(n_nodes, 1), np.int64)
    run_count = np.empty(max(n_nodes, 1), np.int64)
    fill = starts.copy()
    i_low = float(i_range[0])
    i_scale = 255.0 / max(float(i_range[1] - i_range[0]), 1.0)
    try:
        for start, block in columns.iter(("xyz", "rgb", "intensity")):
            n = len(block["xyz"])
            kernels.assign(
                block["xyz"], start, cube_min, scale, top, spread, depth, counts, ids, offsets,
                capacity, node_of[:n],
            )  # fmt: skip
            m = kernels.group_block(
                node_of[:n], start, block["xyz"], origin, block["rgb"], block["intensity"],
                i_low, i_scale, n_nodes, buffers["positions"], buffers["rgb"],
                buffers["intensity"], buffers["index"], present, run_start, run_count,
            )  # fmt: skip
            for node, a, count in zip(
                present[:m].tolist(), run_start[:m].tolist(), run_count[:m].tolist(), strict=True
            ):
                at = int(fill[node])
                for name, (fd, offset, row_bytes) in files.items():
                    data = buffers[name][a : a + count]
                    os.pwrite(fd, data.tobytes(), offset + at * row_bytes)
                fill[node] += count
            report("write", start, n)
    finally:
        for fd, _, _ in files.values():
            os.close(fd)
    manifest = {
        "version": version,
        "source": fingerprint,
        "n_points": n_points,
        "origin": origin.tolist(),
        "cube_min": cube_min.tolist(),
        "cube_size": cube_size,
        "max_depth": depth,
        "capacity": capacity,
        "bounds_min": low.tolist(),
        "bounds_max": high.tolist(),
        "intensity_range": [float(i_range[0]), float(i_range[1])],
        "nodes": _manifest_nodes(
            counts, ids, offsets, depth, starts, sizes, cube_min - origin, cube_size
        ),
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
