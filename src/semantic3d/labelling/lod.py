"""A level-of-detail octree over a scan, built once from its binary cache and reused.

Potree-style: the scan's bounding cube is an octree; each node holds a subsample of the
points of its cube and its children refine it, so a viewer draws coarse nodes first and
loads finer ones where the screen needs them. Every point is in exactly one node.

Which node a point goes to: each point draws a uniform rank ``r`` (a hash of its position
in the scan, so the build does not depend on chunking). Walking from the root, the point
stays in the first node ``n`` on its path where ``r < capacity / count(n)`` (``count`` is
the number of points under ``n``), or where ``n`` is a leaf (at most ``capacity`` points
under it, or the deepest level). Each node then holds about ``capacity`` points, a uniform
random subsample of its cube minus what its ancestors took.

The build streams the cache four times (bounds, cell histogram, node counts, writing) and
holds a fixed-size cell histogram (at most ``8**max_depth`` counters) and one chunk: memory
does not grow with the scan. The folder (``lod-v1/`` inside the cache folder, like the
cache's tile stores) holds::

    lod.json          version, source fingerprint, origin, cube, nodes (bounds, start, count)
    positions.npy     (n, 3) float32 metres, re-centred on ``origin``, grouped by node
    rgb.npy           (n, 3) uint8
    intensity.npy     (n,) uint8, the scan's intensity range stretched to 0..255
    index.npy         (n,) uint32 or int64: each point's position in the cache

It is written in a hidden sibling and renamed into place, and rebuilt when the cache's
``meta.json`` changes.
"""

from __future__ import annotations

import hashlib
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

from semantic3d.core.errors import DataFormatError
from semantic3d.core.pointcloud import PointCloud
from semantic3d.io.cache import iter_cache
from semantic3d.io.cache_meta import META_FILE

__all__ = [
    "DEFAULT_NODE_CAPACITY",
    "LOD_FOLDER",
    "LOD_VERSION",
    "LodIndex",
    "LodNode",
    "NodePoints",
    "build_lod",
    "open_lod",
]

logger = logging.getLogger(__name__)

LOD_VERSION = 1
LOD_FOLDER = f"lod-v{LOD_VERSION}"
DEFAULT_NODE_CAPACITY = 20_000
DEFAULT_MAX_DEPTH = 8
DEFAULT_CHUNK_SIZE = 1 << 20
_MANIFEST = "lod.json"


@dataclass(frozen=True, slots=True)
class LodNode:
    """One octree node: its cube (re-centred metres) and its range in the node-ordered files."""

    id: int
    name: str
    depth: int
    bounds: tuple[float, float, float, float, float, float]
    start: int
    count: int
    children: tuple[int, ...]

    def to_dict(self) -> dict[str, Any]:
        """The JSON form served to the viewer."""
        return {
            "id": self.id,
            "name": self.name,
            "depth": self.depth,
            "bounds": list(self.bounds),
            "start": self.start,
            "count": self.count,
            "children": list(self.children),
        }


@dataclass(frozen=True, slots=True)
class NodePoints:
    """The points of one node: re-centred positions, colours, intensities, cache indices."""

    positions: NDArray[np.float32]
    rgb: NDArray[np.uint8]
    intensity: NDArray[np.uint8]
    indices: NDArray[np.int64]


class LodIndex:
    """An opened level-of-detail folder; node payloads are read from memory maps."""

    def __init__(self, directory: str | Path) -> None:
        self.directory = Path(directory)
        manifest = self.directory / _MANIFEST
        try:
            data = json.loads(manifest.read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError) as exc:
            raise DataFormatError(
                f"expected a level-of-detail manifest, found {exc}", path=str(manifest)
            ) from exc
        if data.get("version") != LOD_VERSION:
            raise DataFormatError(
                f"expected level-of-detail version {LOD_VERSION}, found {data.get('version')!r}",
                path=str(manifest),
            )
        self.source: str = data["source"]
        self.n_points: int = int(data["n_points"])
        self.origin = np.asarray(data["origin"], np.float64)
        self.cube_min = np.asarray(data["cube_min"], np.float64)
        self.cube_size: float = float(data["cube_size"])
        self.max_depth: int = int(data["max_depth"])
        self.capacity: int = int(data["capacity"])
        self.bounds_min = np.asarray(data["bounds_min"], np.float64)
        self.bounds_max = np.asarray(data["bounds_max"], np.float64)
        self.nodes: tuple[LodNode, ...] = tuple(
            LodNode(
                int(n["id"]),
                str(n["name"]),
                int(n["depth"]),
                tuple(float(v) for v in n["bounds"]),  # type: ignore[arg-type]
                int(n["start"]),
                int(n["count"]),
                tuple(int(c) for c in n["children"]),
            )
            for n in data["nodes"]
        )
        self._positions = np.load(self.directory / "positions.npy", mmap_mode="r")
        self._rgb = np.load(self.directory / "rgb.npy", mmap_mode="r")
        self._intensity = np.load(self.directory / "intensity.npy", mmap_mode="r")
        self._index = np.load(self.directory / "index.npy", mmap_mode="r")
        if self._positions.shape != (self.n_points, 3) or self._index.shape != (self.n_points,):
            raise DataFormatError(
                f"expected columns of {self.n_points} points, found {self._positions.shape}",
                path=str(self.directory),
            )

    def node(self, node_id: int) -> LodNode:
        """The node ``node_id``; :class:`KeyError` when there is none."""
        if not 0 <= node_id < len(self.nodes):
            raise KeyError(node_id)
        return self.nodes[node_id]

    def read_node(self, node_id: int) -> NodePoints:
        """The points of node ``node_id`` (private copies)."""
        node = self.node(node_id)
        span = slice(node.start, node.start + node.count)
        return NodePoints(
            np.array(self._positions[span]),
            np.array(self._rgb[span]),
            np.array(self._intensity[span]),
            np.asarray(self._index[span], np.int64),
        )

    def node_indices(self, node_id: int) -> NDArray[np.int64]:
        """Cache positions of the points of node ``node_id``."""
        node = self.node(node_id)
        return np.asarray(self._index[node.start : node.start + node.count], np.int64)

    def hierarchy(self) -> dict[str, Any]:
        """What the viewer loads first: origin, bounds and every node."""
        return {
            "n_points": self.n_points,
            "origin": self.origin.tolist(),
            "bounds_min": (self.bounds_min - self.origin).tolist(),
            "bounds_max": (self.bounds_max - self.origin).tolist(),
            "capacity": self.capacity,
            "nodes": [node.to_dict() for node in self.nodes],
        }


def cache_fingerprint(cache: str | Path) -> str:
    """SHA-256 of the cache's ``meta.json``: changes whenever the cache is rebuilt."""
    meta = Path(cache) / META_FILE
    if not meta.is_file():
        raise DataFormatError(
            f"expected a cache folder holding {META_FILE}, found none", path=str(cache)
        )
    return hashlib.sha256(meta.read_bytes()).hexdigest()


def open_lod(
    cache: str | Path,
    *,
    directory: str | Path | None = None,
    capacity: int = DEFAULT_NODE_CAPACITY,
    max_depth: int = DEFAULT_MAX_DEPTH,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
    progress: Callable[[str, int, int], None] | None = None,
) -> LodIndex:
    """The level-of-detail index of the cache folder ``cache``, built on first use.

    A current index (same cache fingerprint, capacity and depth limit) is reopened;
    otherwise :func:`build_lod` builds it into ``directory`` (default ``cache/lod-v1``;
    the labelling app keeps it in its cache folder instead).
    """
    cache = Path(cache)
    directory = cache / LOD_FOLDER if directory is None else Path(directory)
    fingerprint = cache_fingerprint(cache)
    if (directory / _MANIFEST).is_file():
        try:
            index = LodIndex(directory)
        except (DataFormatError, OSError, KeyError, ValueError):
            index = None
        if index is not None and index.source == fingerprint and index.capacity == capacity:
            return index
    return build_lod(
        cache,
        directory,
        capacity=capacity,
        max_depth=max_depth,
        chunk_size=chunk_size,
        progress=progress,
    )


def _rank(indices: NDArray[np.int64]) -> NDArray[np.float64]:
    """A uniform number in [0, 1) per scan position (splitmix64), independent of chunking."""
    z = indices.astype(np.uint64) + np.uint64(0x9E3779B97F4A7C15)
    with np.errstate(over="ignore"):
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        z = z ^ (z >> np.uint64(31))
    return (z >> np.uint64(11)).astype(np.float64) / float(1 << 53)


def _morton(cells: NDArray[np.int64], depth: int) -> NDArray[np.int64]:
    """Interleave the bits of integer cells ``(n, 3)`` into one key (x highest)."""
    key = np.zeros(cells.shape[0], np.int64)
    for bit in range(depth):
        for axis in range(3):
            key |= ((cells[:, axis] >> bit) & 1) << (3 * bit + 2 - axis)
    return key


def _merge_counts(
    keys: NDArray[np.int64], counts: NDArray[np.int64], more: NDArray[np.int64]
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    new_keys, new_counts = np.unique(more, return_counts=True)
    all_keys = np.concatenate([keys, new_keys])
    merged, inverse = np.unique(all_keys, return_inverse=True)
    total = np.bincount(inverse, weights=np.concatenate([counts, new_counts]))
    return merged, total.astype(np.int64)


class _Octree:
    """The node layout decided from the occupied leaf cells (sparse, Morton keys)."""

    def __init__(
        self,
        leaf_keys: NDArray[np.int64],
        leaf_counts: NDArray[np.int64],
        depth: int,
        capacity: int,
    ) -> None:
        self.depth = depth
        self.capacity = capacity
        keys = [leaf_keys]
        counts = [leaf_counts]
        for _ in range(depth):
            parents, inverse = np.unique(keys[0] >> 3, return_inverse=True)
            keys.insert(0, parents)
            counts.insert(0, np.bincount(inverse, weights=counts[0]).astype(np.int64))
        self.keys = keys
        self.counts = counts
        self.internal = [(c > capacity) & (d < depth) for d, c in enumerate(counts)]
        # A cell is a node when its parent is internal (the root always is a node).
        self.node_ids: list[NDArray[np.int64]] = []
        next_id = 0
        for d in range(depth + 1):
            if d == 0:
                is_node = np.ones(keys[0].size, bool)
            else:
                parent = np.searchsorted(keys[d - 1], keys[d] >> 3)
                is_node = self.internal[d - 1][parent]
            ids = np.full(keys[d].size, -1, np.int64)
            ids[is_node] = np.arange(next_id, next_id + int(is_node.sum()))
            next_id += int(is_node.sum())
            self.node_ids.append(ids)
        self.n_nodes = next_id

    def assign(self, leaf: NDArray[np.int64], ranks: NDArray[np.float64]) -> NDArray[np.int64]:
        """Node id of each point, from its leaf Morton key and rank."""
        node = np.full(leaf.shape[0], -1, np.int64)
        todo = np.arange(leaf.shape[0])
        for d in range(self.depth + 1):
            where = np.searchsorted(self.keys[d], leaf[todo] >> (3 * (self.depth - d)))
            count = self.counts[d][where]
            stay = ~self.internal[d][where] | (ranks[todo] * count < self.capacity)
            node[todo[stay]] = self.node_ids[d][where[stay]]
            todo = todo[~stay]
            if todo.size == 0:
                break
        return node

    def nodes(
        self, starts: NDArray[np.int64], sizes: NDArray[np.int64], cube_min: Any, cube_size: float
    ) -> list[dict[str, Any]]:
        """The manifest entries of every node, in id order (breadth first)."""
        result: list[dict[str, Any]] = []
        names: dict[int, str] = {}
        for d in range(self.depth + 1):
            edge = cube_size / (1 << d)
            for key, node_id in zip(self.keys[d].tolist(), self.node_ids[d].tolist(), strict=True):
                if node_id < 0:
                    continue
                cell = [0, 0, 0]
                for bit in range(d):
                    for axis in range(3):
                        cell[axis] |= ((key >> (3 * bit + 2 - axis)) & 1) << bit
                if d == 0:
                    name = "r"
                    parent = -1
                else:
                    pk = key >> 3
                    parent = int(self.node_ids[d - 1][np.searchsorted(self.keys[d - 1], pk)])
                    name = names[parent] + str(key & 7)
                names[node_id] = name
                low = np.asarray(cube_min) + edge * np.asarray(cell, np.float64)
                result.append(
                    {
                        "id": node_id,
                        "name": name,
                        "depth": d,
                        "bounds": [*low.tolist(), *(low + edge).tolist()],
                        "start": int(starts[node_id]),
                        "count": int(sizes[node_id]),
                        "children": [],
                    }
                )
                if parent >= 0:
                    result[parent]["children"].append(node_id)
        return result


def build_lod(
    cache: str | Path,
    directory: str | Path,
    *,
    capacity: int = DEFAULT_NODE_CAPACITY,
    max_depth: int = DEFAULT_MAX_DEPTH,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
    progress: Callable[[str, int, int], None] | None = None,
) -> LodIndex:
    """Build the level-of-detail index of the cache ``cache`` into ``directory``.

    ``progress(stage, done_points, total_points)`` is called after each chunk of each of
    the four passes (stages ``bounds``, ``histogram``, ``counts``, ``write``). The folder
    is written under a hidden name and renamed into place, replacing an older index.
    """
    if capacity < 1:
        raise ValueError(f"capacity: expected a positive number of points, found {capacity}")
    if not 0 <= max_depth <= 9:
        raise ValueError(f"max_depth: expected 0..9, found {max_depth}")
    cache = Path(cache)
    directory = Path(directory)
    fingerprint = cache_fingerprint(cache)

    def chunks(stage: str, total: int) -> Iterator[tuple[int, PointCloud]]:
        done = 0
        for chunk in iter_cache(cache, chunk_size=chunk_size):
            yield done, chunk
            done += chunk.n_points
            if progress is not None:
                progress(stage, done, total)

    # Pass 1: bounds and intensity range.
    low = np.full(3, np.inf)
    high = np.full(3, -np.inf)
    i_low, i_high = np.inf, -np.inf
    n_points = 0
    for _, chunk in chunks("bounds", 0):
        n_points += chunk.n_points
        if chunk.n_points:
            low = np.minimum(low, chunk.xyz.min(axis=0))
            high = np.maximum(high, chunk.xyz.max(axis=0))
            i_low = min(i_low, float(chunk.intensity.min()))
            i_high = max(i_high, float(chunk.intensity.max()))
    if n_points == 0:
        low = high = np.zeros(3)
        i_low = i_high = 0.0
    origin = np.round((low + high) / 2.0)
    cube_size = float(max((high - low).max(), 1e-3)) * (1 + 1e-9)
    cube_min = low
    depth = max_depth
    g = 1 << depth

    def leaf_cells(xyz: NDArray[np.float64]) -> NDArray[np.int64]:
        cells = np.floor((xyz - cube_min) / cube_size * g).astype(np.int64)
        return _morton(np.clip(cells, 0, g - 1), depth)

    # Pass 2: occupied leaf cells and their counts (sparse: at most min(n, 8**depth)).
    leaf_keys = np.empty(0, np.int64)
    leaf_counts = np.empty(0, np.int64)
    for _, chunk in chunks("histogram", n_points):
        leaf_keys, leaf_counts = _merge_counts(leaf_keys, leaf_counts, leaf_cells(chunk.xyz))
    tree = _Octree(leaf_keys, leaf_counts, depth, capacity)
    del leaf_keys, leaf_counts

    # Pass 3: points per node.
    sizes = np.zeros(tree.n_nodes, np.int64)
    for start, chunk in chunks("counts", n_points):
        ids = tree.assign(leaf_cells(chunk.xyz), _rank(np.arange(start, start + chunk.n_points)))
        sizes += np.bincount(ids, minlength=tree.n_nodes)
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)

    # Pass 4: write every point at its node's next free place.
    directory.parent.mkdir(parents=True, exist_ok=True)
    staging = directory.parent / f".{directory.name}.partial-{uuid.uuid4().hex[:12]}"
    staging.mkdir()
    try:
        index_dtype = np.dtype(np.uint32) if n_points < 2**32 else np.dtype(np.int64)
        columns: dict[str, tuple[np.dtype[Any], tuple[int, ...]]] = {
            "positions": (np.dtype(np.float32), (n_points, 3)),
            "rgb": (np.dtype(np.uint8), (n_points, 3)),
            "intensity": (np.dtype(np.uint8), (n_points,)),
            "index": (index_dtype, (n_points,)),
        }
        files = {
            name: _open_column(staging / f"{name}.npy", *spec) for name, spec in columns.items()
        }
        fill = starts.copy()
        span = max(i_high - i_low, 1.0)
        try:
            for start, chunk in chunks("write", n_points):
                indices = np.arange(start, start + chunk.n_points, dtype=np.int64)
                ids = tree.assign(leaf_cells(chunk.xyz), _rank(indices))
                order = np.argsort(ids, kind="stable")
                ids = ids[order]
                values = {
                    "positions": (chunk.xyz[order] - origin).astype(np.float32),
                    "rgb": chunk.rgb[order],
                    "intensity": np.clip(
                        (chunk.intensity[order] - i_low) * (255.0 / span), 0, 255
                    ).astype(np.uint8),
                    "index": indices[order].astype(index_dtype),
                }
                present, first, counts = np.unique(ids, return_index=True, return_counts=True)
                for node_id, a, n in zip(
                    present.tolist(), first.tolist(), counts.tolist(), strict=True
                ):
                    at = int(fill[node_id])
                    for name, (fd, offset, row_bytes) in files.items():
                        block = np.ascontiguousarray(values[name][a : a + n])
                        os.pwrite(fd, block.data, offset + at * row_bytes)
                    fill[node_id] += n
        finally:
            for fd, _, _ in files.values():
                os.close(fd)
        manifest = {
            "version": LOD_VERSION,
            "source": fingerprint,
            "n_points": n_points,
            "origin": origin.tolist(),
            "cube_min": cube_min.tolist(),
            "cube_size": cube_size,
            "max_depth": depth,
            "capacity": capacity,
            "bounds_min": low.tolist(),
            "bounds_max": high.tolist(),
            "intensity_range": [i_low, i_high],
            "nodes": tree.nodes(starts, sizes, cube_min - origin, cube_size),
        }
        (staging / _MANIFEST).write_text(json.dumps(manifest) + "\n", encoding="utf-8")
        _replace_folder(staging, directory)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    logger.info("%s: %d points in %d nodes", directory, n_points, tree.n_nodes)
    return LodIndex(directory)


def _open_column(path: Path, dtype: np.dtype[Any], shape: tuple[int, ...]) -> tuple[int, int, int]:
    """Create a ``.npy`` file of ``shape``; return its descriptor, data offset and row size."""
    array = np.lib.format.open_memmap(path, mode="w+", dtype=dtype, shape=shape)
    offset = int(array.offset)
    del array
    row_bytes = dtype.itemsize * (shape[1] if len(shape) > 1 else 1)
    return os.open(path, os.O_WRONLY), offset, row_bytes


def _replace_folder(staging: Path, destination: Path) -> None:
    if destination.exists():
        retired = destination.parent / f".{destination.name}.old-{uuid.uuid4().hex[:12]}"
        destination.rename(retired)
        staging.rename(destination)
        shutil.rmtree(retired, ignore_errors=True)
    else:
        staging.rename(destination)
