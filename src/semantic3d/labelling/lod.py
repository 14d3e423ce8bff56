"""A level-of-detail octree over a scan, built once from its binary cache and reused.

Potree-style: the scan's bounding cube is an octree; each node holds a subsample of the
points of its cube and its children refine it, so a viewer draws coarse nodes first and
loads finer ones where the screen needs them. Every point is in exactly one node.

Which node a point goes to: each point draws a uniform rank ``r`` (a hash of its position
in the scan, so the build does not depend on chunking). Walking from the root, the point
stays in the first node ``n`` on its path where ``r < capacity / count(n)`` (``count`` is
the number of points under ``n``), or where ``n`` is a leaf (at most ``capacity`` points
under it). Each node then holds about ``capacity`` points, a uniform random subsample of
its cube minus what its ancestors took, and at most ``capacity`` (below the octree's
:data:`~semantic3d.labelling.lod_build.POSITION_DEPTH`, where cells are smaller than the
float32 copy's resolution, a node's children split its points by a hash of their scan
positions and share its cube).

The build (:mod:`~semantic3d.labelling.lod_build`) streams the cache in compiled passes
(bounds, cell histogram, a pass or two refining over-full cells into deeper levels, node
sizes, writing) and holds dense octree levels (``8**dense_depth`` leaf counters), the
refining blocks and one block: memory does not grow with the scan. The folder (the
labelling app keeps it in its cache folder) holds::

    lod.json          version, source fingerprint, origin, cube, nodes (bounds, start, count)
    positions.npy     (n, 3) float32 metres, re-centred on ``origin``, grouped by node
    rgb.npy           (n, 3) uint8
    intensity.npy     (n,) uint8, the scan's intensity range stretched to 0..255
    index.npy         (n,) uint32: each point's position in the cache

It is written in a hidden sibling and renamed into place, and rebuilt when the cache's
``meta.json`` changes.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import shutil
import threading
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from semantic3d.core.errors import DataFormatError
from semantic3d.io.cache_meta import META_FILE
from semantic3d.labelling.lod_build import DENSE_DEPTH_LIMIT, build_lod_files, replace_folder

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

LOD_VERSION = 2
"""2: nodes deeper than the dense levels, none above the capacity (1: at most 8 levels)."""
LOD_FOLDER = f"lod-v{LOD_VERSION}"
DEFAULT_NODE_CAPACITY = 20_000
DEFAULT_DENSE_DEPTH = 8
DEFAULT_CHUNK_SIZE = 1 << 21
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
    """An opened level-of-detail folder; node payloads are read with positional reads.

    Not memory maps: the pages a map has touched count as the process's resident memory,
    so a server that had shown most of a 10**8-point scan would look 2 GB large.
    """

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
        self.dense_depth: int = int(data["dense_depth"])
        self.position_depth: int = int(data["position_depth"])
        self.max_depth: int = int(data["max_depth"])
        """The deepest node's depth."""
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
        self.node_bounds = np.array([n.bounds for n in self.nodes], np.float64).reshape(-1, 6)
        """Every node's cube (re-centred x0, y0, z0, x1, y1, z1), by id."""
        self.node_starts = np.array([n.start for n in self.nodes], np.int64)
        self.node_counts = np.array([n.count for n in self.nodes], np.int64)
        self._columns: dict[str, tuple[int, int, np.dtype[Any], tuple[int, ...]]] = {}
        self._lock = threading.Lock()
        for name, tail in (("positions", (3,)), ("rgb", (3,)), ("intensity", ()), ("index", ())):
            path = self.directory / f"{name}.npy"
            column = np.load(path, mmap_mode="r")
            if column.shape != (self.n_points, *tail):
                raise DataFormatError(
                    f"expected a column of {self.n_points} points, found shape {column.shape}",
                    path=str(path),
                )
            offset, dtype = int(column.offset), column.dtype
            del column
            self._columns[name] = (os.open(path, os.O_RDONLY), offset, dtype, tail)

    def _read(self, name: str, start: int, count: int) -> NDArray[Any]:
        descriptor, offset, dtype, tail = self._columns[name]
        row = dtype.itemsize * int(np.prod(tail, dtype=np.int64))
        out = np.empty((count, *tail), dtype)
        view = memoryview(out.reshape(-1).view(np.uint8))  # type: ignore[arg-type]
        got = 0
        while got < count * row:
            read = os.preadv(descriptor, [view[got:]], offset + start * row + got)
            if not read:
                raise DataFormatError(
                    f"expected {count * row} bytes at point {start}, found {got}",
                    path=str(self.directory / f"{name}.npy"),
                )
            got += read
        return out

    def close(self) -> None:
        """Close the column files."""
        with self._lock:
            for descriptor, *_ in self._columns.values():
                with contextlib.suppress(OSError):
                    os.close(descriptor)
            self._columns = {}

    def __del__(self) -> None:
        with contextlib.suppress(Exception):
            self.close()

    def node(self, node_id: int) -> LodNode:
        """The node ``node_id``; :class:`KeyError` when there is none."""
        if not 0 <= node_id < len(self.nodes):
            raise KeyError(node_id)
        return self.nodes[node_id]

    def read_node(self, node_id: int) -> NodePoints:
        """The points of node ``node_id`` (private copies)."""
        node = self.node(node_id)
        return NodePoints(
            self._read("positions", node.start, node.count),
            self._read("rgb", node.start, node.count),
            self._read("intensity", node.start, node.count),
            self._read("index", node.start, node.count).astype(np.int64),
        )

    def iter_positions(
        self, node_id: int, *, chunk_points: int = 1 << 20
    ) -> Iterator[tuple[NDArray[np.float32], NDArray[Any]]]:
        """``(float32 re-centred positions, uint32 scan indices)`` of a node, in chunks."""
        node = self.node(node_id)
        for start in range(node.start, node.start + node.count, chunk_points):
            count = min(chunk_points, node.start + node.count - start)
            yield self._read("positions", start, count), self._read("index", start, count)

    def node_indices(self, node_id: int) -> NDArray[np.int64]:
        """Cache positions of the points of node ``node_id``."""
        node = self.node(node_id)
        return self._read("index", node.start, node.count).astype(np.int64)

    def read_indices(self, start: int, count: int) -> NDArray[np.uint32]:
        """Cache positions (uint32) of the points ``start .. start + count`` in node order
        (node ``n`` holds ``n.start .. n.start + n.count``: consecutive nodes, one read)."""
        return self._read("index", start, count)

    def read_positions(self, start: int, count: int) -> NDArray[np.float32]:
        """Float32 re-centred positions of the points ``start .. start + count`` in node order."""
        return self._read("positions", start, count)

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
    dense_depth: int = DEFAULT_DENSE_DEPTH,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
    progress: Callable[[str, int, int], None] | None = None,
) -> LodIndex:
    """The level-of-detail index of the cache folder ``cache``, built on first use.

    A current index (same format version, cache fingerprint, capacity and dense depth) is
    reopened; otherwise :func:`build_lod` builds it into ``directory`` (default
    ``cache/lod-v{LOD_VERSION}``; the labelling app keeps it in its cache folder instead).
    An index of an older format version is rebuilt.
    """
    cache = Path(cache)
    directory = cache / LOD_FOLDER if directory is None else Path(directory)
    fingerprint = cache_fingerprint(cache)
    if (directory / _MANIFEST).is_file():
        try:
            index = LodIndex(directory)
        except (DataFormatError, OSError, KeyError, ValueError):
            index = None
        if (
            index is not None
            and index.source == fingerprint
            and index.capacity == capacity
            and index.dense_depth == dense_depth
        ):
            return index
    return build_lod(
        cache,
        directory,
        capacity=capacity,
        dense_depth=dense_depth,
        chunk_size=chunk_size,
        progress=progress,
    )


def build_lod(
    cache: str | Path,
    directory: str | Path,
    *,
    capacity: int = DEFAULT_NODE_CAPACITY,
    dense_depth: int = DEFAULT_DENSE_DEPTH,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
    progress: Callable[[str, int, int], None] | None = None,
) -> LodIndex:
    """Build the level-of-detail index of the cache ``cache`` into ``directory``.

    ``progress(stage, done_points, total_points)`` is called after each chunk of each
    pass (stages ``bounds``, ``histogram``, ``refine`` (once per refining pass, only when
    cells are over-full), ``counts``, ``write``). The folder is written under a hidden name
    and renamed into place, replacing an older index.
    """
    if capacity < 1:
        raise ValueError(f"capacity: expected a positive number of points, found {capacity}")
    if not 0 <= dense_depth <= DENSE_DEPTH_LIMIT:
        raise ValueError(f"dense_depth: expected 0..{DENSE_DEPTH_LIMIT}, found {dense_depth}")
    cache = Path(cache)
    directory = Path(directory)
    fingerprint = cache_fingerprint(cache)

    directory.parent.mkdir(parents=True, exist_ok=True)
    staging = directory.parent / f".{directory.name}.partial-{uuid.uuid4().hex[:12]}"
    staging.mkdir()
    try:
        n_nodes = build_lod_files(
            cache,
            staging,
            capacity=capacity,
            dense_depth=dense_depth,
            fingerprint=fingerprint,
            version=LOD_VERSION,
            block_points=chunk_size,
            progress=progress,
        )
        replace_folder(staging, directory)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    logger.info("%s: %d nodes", directory, n_nodes)
    return LodIndex(directory)
