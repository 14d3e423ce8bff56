"""A scan spilled once into square XY tiles on disk; any tile read with a halo of any width.

:func:`build_tile_store` streams point chunks once into the tiles of a
:class:`~semantic3d.spatial.grid.TileGrid` (spilling to one file per tile past a memory
budget), then seals the store: one memory-mapped ``points.npy`` holding every point
grouped by tile (tiles sorted, scan order inside a tile; 44 bytes a point: coordinates,
position in the scan, intensity, colour, label) and a spatial index. Each tile is cut into
``subdivisions × subdivisions`` sub-cells; ``order.npy`` lists a tile's points sub-cell by
sub-cell (row-major) and ``offsets.npy`` holds where each sub-cell starts. A tile's *core*
is its own range, in scan order; its *halo* of width ``h`` is every point of the other
tiles within ``h`` of the tile's rectangle, read from the neighbours' sub-cells that can
hold such points only: a thin halo costs a thin strip of reading, and one store serves
every halo width its users need (k-NN features, CNN cubes, label transfer between scans).

A :class:`TileStore` holds nothing but its folder's path and manifest: it pickles to a few
hundred bytes and reopens in another process, so a :class:`~semantic3d.spatial.job.TileJob`
can travel to a worker that sees the same folder. Memory while building is bounded by
``buffer_points``; while reading, by the tiles read. Binning, the sub-cell index and box
reads are compiled counting sorts and scans (:mod:`semantic3d.spatial._kernels`), with
the results the numpy expressions they replace give (``tests/spatial``); tiles are
sealed at the same time on the thread budget, each written at its place (the same
files for any number of threads). Sealing a tile holds its sub-cell codes and order (6
bytes a point) and a window of its records, not the tile: the densest tile of a station
holds over half of its points.
"""

from __future__ import annotations

import json
import logging
import math
import os
import shutil
import tempfile
import threading
import uuid
from collections import defaultdict
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from semantic3d.core.errors import DataFormatError, ShapeError
from semantic3d.core.pointcloud import PointCloud
from semantic3d.core.threads import map_in_threads, serial_section, thread_budget
from semantic3d.spatial.grid import Bounds, TileGrid, TileKey

if TYPE_CHECKING:
    from semantic3d.spatial.job import TileJob

__all__ = [
    "STORE_VERSION",
    "TemporaryTileStore",
    "TileData",
    "TilePoints",
    "TileStore",
    "TileStoreWriter",
    "build_tile_store",
    "xyz_label_rows",
]

logger = logging.getLogger(__name__)

STORE_VERSION = 1
"""Version of the folder layout; a store of another version is refused."""

MANIFEST_FILE = "tiles.json"
POINTS_FILE = "points.npy"
ORDER_FILE = "order.npy"
OFFSETS_FILE = "offsets.npy"
STARTS_FILE = "starts.npy"
KEYS_FILE = "keys.npy"
DEFAULT_SUBDIVISIONS = 32
REMAP_BYTES = 1 << 27
"""Records read through one mapping of a store's files before they are mapped anew (a
process, a Dask worker among them, keeps at most about this much of a store resident)."""
DEFAULT_BUFFER_POINTS = 1 << 22
_SEAL_WINDOW = 1 << 16
"""Records of a spilled tile read and written at a time while sealing (2.9 MB: the
window stays in the cache between its read and its write)."""
_MAX_TILE_SPAN = 1 << 31
"""Tiles along x or y that one chunk may span (their numbers fit 62 bits)."""
_SMALL_TILE_POINTS = 4096
"""Tiles this small are filtered whole: cheaper than gathering their sub-cells."""

_BASE_FIELDS: list[tuple[Any, ...]] = [
    ("xyz", np.float64, (3,)),
    ("index", np.int64),
    ("intensity", np.int32),
    ("rgb", np.uint8, (3,)),
]


def record_dtype(*, with_labels: bool) -> np.dtype[Any]:
    """The packed record of one stored point."""
    fields = [*_BASE_FIELDS, ("labels", np.uint8)] if with_labels else _BASE_FIELDS
    return np.dtype(fields)


@dataclass(frozen=True, slots=True)
class TilePoints:
    """Points read from a store.

    Attributes:
        cloud: the points (coordinates in absolute metres, as given to the store).
        indices: ``(n,)`` int64 position of each point in the stream the store was built from.
    """

    cloud: PointCloud
    indices: NDArray[np.int64]

    @property
    def n_points(self) -> int:
        """Number of points."""
        return self.cloud.n_points

    @classmethod
    def from_records(cls, records: NDArray[Any]) -> TilePoints:
        """Points over packed records, without copying: read-only strided views.

        Columns of a tile read from a folder store are views of its memory map (read on
        first touch); ``np.ascontiguousarray`` or ``cloud[...]`` makes private copies.
        """
        names = records.dtype.names or ()

        def column(name: str) -> NDArray[Any]:
            view = records[name]
            view.flags.writeable = False
            return view

        cloud = PointCloud(
            column("xyz"),
            column("intensity"),
            column("rgb"),
            column("labels") if "labels" in names else None,
        )
        return cls(cloud, column("index"))

    def copied(self, *, positions: bool = True) -> TilePoints:
        """Private contiguous copies of the coordinates, labels and indices (intensity and
        colours stay as they are), copied on every thread: numpy copies a strided column
        on one thread. ``positions=False`` leaves the coordinates as they are too."""
        from semantic3d.spatial._kernels import copy_columns

        cloud = self.cloud
        n = cloud.n_points
        xyz = np.empty((n if positions else 0, 3), np.float64)
        labels = None if cloud.labels is None else np.empty(n, np.uint8)
        indices = np.empty(n, np.int64)
        copy_columns(
            cloud.xyz,
            np.empty(0, np.uint8) if cloud.labels is None else cloud.labels,
            self.indices,
            xyz,
            np.empty(0, np.uint8) if labels is None else labels,
            indices,
        )
        return TilePoints(
            PointCloud(xyz if positions else cloud.xyz, cloud.intensity, cloud.rgb, labels),
            indices,
        )


def xyz_label_rows(points: TilePoints) -> NDArray[np.float64]:
    """``(n, 4)`` float64 rows ``x y z label`` of ``points`` (label 0 without labels).

    Contiguous rows are what neighbour searches and sorts take; built by one compiled
    pass over the records' strided columns.
    """
    from semantic3d.spatial._kernels import xyz_label_rows as fill

    rows = np.empty((points.n_points, 4), dtype=np.float64)
    labels = points.cloud.labels
    fill(points.cloud.xyz, np.empty(0, np.uint8) if labels is None else labels, rows)
    return rows


def _as_bytes(records: NDArray[Any]) -> NDArray[np.uint8]:
    """Contiguous records as an ``(n, itemsize)`` byte array (same memory)."""
    raw: NDArray[np.uint8] = records.view(np.uint8).reshape(records.shape[0], records.itemsize)
    return raw


@dataclass(frozen=True, slots=True)
class TileData:
    """A tile's own points and its halo.

    Attributes:
        tile: the tile's key.
        bounds: the tile's rectangle.
        halo_m: width of the halo read around it.
        core: the points of the tile, in scan order.
        halo: the points of other tiles within ``halo_m`` of ``bounds``.
    """

    tile: TileKey
    bounds: Bounds
    halo_m: float
    core: TilePoints
    halo: TilePoints


class TileStore:
    """A sealed tile store folder, opened read-only (see the module docs).

    Args:
        directory: a folder written by :func:`build_tile_store`.

    Raises:
        DataFormatError: no manifest, another layout version, or missing tile files.
    """

    directory: Path | None
    """The store's folder; None for a small store held in memory."""

    def __init__(self, directory: str | Path) -> None:
        self.directory = Path(directory)
        manifest = self.directory / MANIFEST_FILE
        if not manifest.is_file():
            raise DataFormatError(
                f"expected a tile store holding {MANIFEST_FILE}, found none",
                path=str(self.directory),
            )
        try:
            data = json.loads(manifest.read_text(encoding="utf-8"))
            version = int(data["version"])
        except (ValueError, KeyError, TypeError) as exc:
            raise DataFormatError(
                f"expected a tile manifest, found {exc!r}", path=str(manifest)
            ) from exc
        if version != STORE_VERSION:
            raise DataFormatError(
                f"expected tile store version {STORE_VERSION}, found {version}", path=str(manifest)
            )
        self.grid = TileGrid.from_dict(data["grid"])
        self.subdivisions = int(data["subdivisions"])
        self.n_points = int(data["n_points"])
        self.has_labels = bool(data["has_labels"])
        self.metadata: dict[str, Any] = dict(data.get("metadata", {}))
        self._dtype = record_dtype(with_labels=self.has_labels)
        keys = np.load(self.directory / KEYS_FILE)
        self._offsets: NDArray[np.int64] = np.load(self.directory / OFFSETS_FILE)
        self._starts: NDArray[np.int64] = np.load(self.directory / STARTS_FILE)
        self.tiles: tuple[TileKey, ...] = tuple((int(x), int(y)) for x, y in keys)
        """Non-empty tiles, sorted."""
        self._row = {tile: row for row, tile in enumerate(self.tiles)}
        self._points: NDArray[Any] | None = None
        self._order: NDArray[np.int32] | None = None
        self._read_bytes = 0
        self._maps_lock = threading.Lock()  # tiles are read on several threads at once
        if self._starts.shape != (len(self.tiles) + 1,) or int(self._starts[-1]) != self.n_points:
            raise DataFormatError(
                f"expected {self.n_points} points in {len(self.tiles)} tiles, found an index "
                "that disagrees",
                path=str(self.directory),
            )

    @classmethod
    def _in_memory(
        cls,
        *,
        grid: TileGrid,
        subdivisions: int,
        tiles: list[TileKey],
        offsets: NDArray[np.int64],
        starts: NDArray[np.int64],
        points: NDArray[Any],
        order: NDArray[np.int32],
        metadata: dict[str, Any],
    ) -> TileStore:
        """A store held in memory (a small temporary store; it cannot be pickled)."""
        store = cls.__new__(cls)
        store.directory = None
        store.grid = grid
        store.subdivisions = subdivisions
        store.n_points = int(points.shape[0])
        store.has_labels = "labels" in (points.dtype.names or ())
        store.metadata = metadata
        store._dtype = points.dtype
        store._offsets = offsets
        store._starts = starts
        store.tiles = tuple(tiles)
        store._row = {tile: row for row, tile in enumerate(store.tiles)}
        store._points = points
        store._order = order
        store._read_bytes = 0
        store._maps_lock = threading.Lock()
        return store

    def _arrays(self, touching: int = 0) -> tuple[NDArray[Any], NDArray[np.int32]]:
        """The memory maps of the points and of the sub-cell order, about to be read for
        ``touching`` records; opened anew after every :data:`REMAP_BYTES` read, so that the
        pages read stop counting as this process's memory once nothing holds them (a
        mapping keeps every page it was read through resident: the whole store, in the
        end). A read of more than that gets maps of its own, let go of with the arrays
        read through them (a scan's densest tile is a gigabyte of pages, which the maps
        kept would hold until the next read). Safe on several threads at once: a thread
        reopening the maps does not take them from under another (the maps it returns
        stay valid while held)."""
        with self._maps_lock:
            if self.directory is not None:
                if touching * self._dtype.itemsize > REMAP_BYTES:
                    return self._opened()
                self._read_bytes += touching * self._dtype.itemsize
                if self._read_bytes > REMAP_BYTES:
                    self._points = self._order = None
                    self._read_bytes = touching * self._dtype.itemsize
            if self._points is None or self._order is None:
                self._points, self._order = self._opened()
            return self._points, self._order

    def _opened(self) -> tuple[NDArray[Any], NDArray[np.int32]]:
        """New memory maps of the points and of the sub-cell order."""
        folder = self._folder()
        try:
            # Plain arrays over the maps: slicing a np.memmap subclass costs ~10 µs.
            points = np.asarray(np.load(folder / POINTS_FILE, mmap_mode="r"))
            order = np.asarray(np.load(folder / ORDER_FILE, mmap_mode="r"))
        except (OSError, ValueError) as exc:
            raise DataFormatError(
                f"expected the store's point files, found {exc}", path=str(folder)
            ) from exc
        if points.shape != (self.n_points,) or points.dtype != self._dtype:
            raise DataFormatError(
                f"expected {self.n_points} records of {self._dtype}, found "
                f"{points.shape} {points.dtype}",
                path=str(folder / POINTS_FILE),
            )
        return points, order

    def __reduce__(self) -> tuple[Any, tuple[str]]:
        return (TileStore, (str(self._folder()),))

    def __repr__(self) -> str:
        where = "in memory" if self.directory is None else repr(str(self.directory))
        return f"TileStore({where}, {len(self.tiles)} tiles, {self.n_points} points)"

    def _folder(self) -> Path:
        if self.directory is None:
            raise TypeError(
                "a tile store held in memory stays in its process: build it in a folder"
            )
        return self.directory

    def __contains__(self, tile: object) -> bool:
        return tile in self._row

    def count(self, tile: TileKey) -> int:
        """Points in ``tile`` (0 for an empty tile)."""
        row = self._row.get(tile)
        return 0 if row is None else int(self._starts[row + 1] - self._starts[row])

    def sub_cell_counts(self, tile: TileKey) -> NDArray[np.int64]:
        """``(subdivisions, subdivisions)`` points of each sub-cell of ``tile``, indexed
        ``[x, y]`` (zeros for an empty tile): where a tile is dense, without reading it."""
        n_sub = self.subdivisions
        row = self._row.get(tile)
        if row is None:
            return np.zeros((n_sub, n_sub), np.int64)
        counts: NDArray[np.int64] = np.diff(self._offsets[row]).reshape(n_sub, n_sub)
        return counts

    @property
    def tile_size_m(self) -> float:
        """Edge of a tile."""
        return self.grid.tile_size_m

    def _records(self, tile: TileKey) -> tuple[NDArray[Any], NDArray[np.int32]]:
        """Memory-mapped records of ``tile`` and their sub-cell order (local indices)."""
        row = self._row[tile]
        begin, end = int(self._starts[row]), int(self._starts[row + 1])
        points, order = self._arrays(end - begin)
        return points[begin:end], order[begin:end]

    def read_core(self, tile: TileKey) -> TilePoints:
        """The points of ``tile`` in the order they were streamed (empty for an empty tile)."""
        if tile not in self._row:
            return TilePoints.from_records(np.empty(0, self._dtype))
        return TilePoints.from_records(self._records(tile)[0])

    def iter_core_parts(self, tile: TileKey, part_points: int) -> Iterator[TilePoints]:
        """The points of ``tile`` in the order they were streamed, ``part_points`` at a
        time: a part's pages of the store stay resident only until the next
        :data:`REMAP_BYTES` have been read, so a tile of any size is read in bounded
        memory (:meth:`read_core` holds the whole tile's while its points are held)."""
        if part_points < 1:
            raise ShapeError(f"part_points: expected at least 1, found {part_points}")
        row = self._row.get(tile)
        if row is None:
            return
        begin, end = int(self._starts[row]), int(self._starts[row + 1])
        for start in range(begin, end, part_points):
            stop = min(end, start + part_points)
            points, _ = self._arrays(stop - start)
            yield TilePoints.from_records(points[start:stop])

    def read_halo(self, tile: TileKey, halo_m: float) -> TilePoints:
        """Points of the other tiles within ``halo_m`` of ``tile``'s rectangle (edges included).

        Neighbour by neighbour, in tile order; inside a neighbour, sub-cell by sub-cell.
        """
        if not (math.isfinite(halo_m) and halo_m >= 0):
            raise ShapeError(f"halo_m: expected a finite width >= 0, found {halo_m}")
        parts = [
            part
            for other, box in self._halo_boxes(tile, halo_m)
            if (part := self._box_indices(other, box)).size
        ]
        if not parts:
            return TilePoints.from_records(np.empty(0, self._dtype))
        return self._take(parts)

    def read(self, tile: TileKey, *, halo_m: float = 0.0) -> TileData:
        """The core and the halo of ``tile``."""
        return TileData(
            tile,
            self.grid.tile_bounds(tile),
            halo_m,
            self.read_core(tile),
            self.read_halo(tile, halo_m),
        )

    def read_box(self, box: Bounds) -> TilePoints:
        """Every point inside the rectangle ``box`` (edges included), tile by tile."""
        parts = [
            part for other in self.tiles_near(box) if (part := self._box_indices(other, box)).size
        ]
        if not parts:
            return TilePoints.from_records(np.empty(0, self._dtype))
        return self._take(parts)

    def read_box_parts(
        self, box: Bounds, *, tiles: Iterable[TileKey] | None = None
    ) -> Iterator[tuple[TileKey, TilePoints]]:
        """The points inside the rectangle ``box`` (edges included) of each tile holding
        some (of ``tiles`` only, when given), tile by tile, in tile order; inside a tile in
        the order they were streamed."""
        wanted = None if tiles is None else set(tiles)
        for other in self.tiles_near(box):
            if wanted is not None and other not in wanted:
                continue
            positions = self._box_indices(other, box)
            if positions.size:
                yield other, self._take([positions])

    def tiles_near(self, box: Bounds) -> list[TileKey]:
        """The non-empty tiles that can hold points of the rectangle ``box``, in tile order
        (its tiles and a ring around them: a point on a tile's edge may belong to either)."""
        x_min, y_min, x_max, y_max = box
        size = self.grid.tile_size_m
        x0, y0 = self.grid.origin_xy
        low = (math.floor((x_min - x0) / size) - 1, math.floor((y_min - y0) / size) - 1)
        high = (math.floor((x_max - x0) / size) + 1, math.floor((y_max - y0) / size) + 1)
        return [
            other
            for other in self.tiles
            if low[0] <= other[0] <= high[0] and low[1] <= other[1] <= high[1]
        ]

    def jobs(self, *, halo_m: float = 0.0) -> tuple[TileJob, ...]:
        """One picklable job per non-empty tile, in tile order."""
        from semantic3d.spatial.job import TileJob

        return tuple(
            TileJob(str(self._folder()), tile, self.grid.tile_bounds(tile), halo_m)
            for tile in self.tiles
        )

    def iter_tiles(self, *, halo_m: float = 0.0) -> Iterator[TileData]:
        """Every non-empty tile with its halo, in tile order."""
        for tile in self.tiles:
            yield self.read(tile, halo_m=halo_m)

    # -- halo geometry -------------------------------------------------------------------
    def _halo_boxes(self, tile: TileKey, halo_m: float) -> Iterator[tuple[TileKey, Bounds]]:
        if halo_m == 0:
            return
        x_min, y_min, x_max, y_max = self.grid.tile_bounds(tile)
        box = (x_min - halo_m, y_min - halo_m, x_max + halo_m, y_max + halo_m)
        rings = max(1, math.ceil(halo_m / self.grid.tile_size_m))
        if (2 * rings + 1) ** 2 > 4 * len(self.tiles):  # a wide halo: scan the tile list
            candidates: Iterable[TileKey] = (
                other
                for other in self.tiles
                if abs(other[0] - tile[0]) <= rings and abs(other[1] - tile[1]) <= rings
            )
        else:
            candidates = (
                (tile[0] + dx, tile[1] + dy)
                for dx in range(-rings, rings + 1)
                for dy in range(-rings, rings + 1)
            )
        for other in candidates:
            if other != tile and other in self._row:
                yield other, box

    def _box_indices(self, tile: TileKey, box: Bounds) -> NDArray[np.int64]:
        """Store positions, ascending, of the points of ``tile`` inside ``box``, found
        through the sub-cell index."""
        from semantic3d.spatial._kernels import select_in_box

        row = self._row[tile]
        n_sub = self.subdivisions
        t_x0, t_y0, _, _ = self.grid.tile_bounds(tile)
        sub = self.grid.tile_size_m / n_sub

        def span(low: float, high: float, start: float) -> tuple[int, int]:
            # The very expression of the assignment (_kernels.sub_cell_codes): IEEE
            # subtraction and division round monotonically, so low <= x implies
            # floor((low - start) / sub) <= the point's sub-cell, and no slack is needed.
            first = max(0, math.floor((low - start) / sub))
            last = min(n_sub - 1, math.floor((high - start) / sub))
            return first, last

        sx0, sx1 = span(box[0], box[2], t_x0)
        sy0, sy1 = span(box[1], box[3], t_y0)
        if sx0 > sx1 or sy0 > sy1:
            return np.empty(0, np.int64)
        begin, end = int(self._starts[row]), int(self._starts[row + 1])
        points, order = self._arrays(end - begin)
        whole = sx0 == 0 and sy0 == 0 and sx1 == n_sub - 1 and sy1 == n_sub - 1
        if whole or end - begin <= _SMALL_TILE_POINTS:
            sx0 = -1  # test every point: cheaper than walking the sub-cells
        local = select_in_box(
            points["xyz"][begin:end],
            order[begin:end],
            self._offsets[row],
            n_sub,
            np.array([sx0, sx1, sy0, sy1], np.int64),
            np.array(box, np.float64),
        )
        return local + begin

    def _take(self, positions: list[NDArray[np.int64]]) -> TilePoints:
        """The records at ``positions`` (lists of store positions), in that order."""
        joined = positions[0] if len(positions) == 1 else np.concatenate(positions)
        points, _ = self._arrays(joined.size)
        return TilePoints.from_records(np.take(points, joined))


def _write_at(fd: int, values: NDArray[Any], offset: int) -> None:
    """Write the bytes of contiguous ``values`` at ``offset`` of ``fd`` (positioned writes
    of several threads do not disturb one another)."""
    view = values.data.cast("B")
    while view.nbytes:
        written = os.pwrite(fd, view, offset)
        view, offset = view[written:], offset + written


def _write_npy_header(stream: Any, dtype: np.dtype[Any], n: int) -> None:
    """The ``.npy`` header of a one-dimensional array of ``n`` records of ``dtype``."""
    header = {
        "descr": np.lib.format.dtype_to_descr(dtype),
        "fortran_order": False,
        "shape": (n,),
    }
    np.lib.format.write_array_header_1_0(stream, header)


class TileStoreWriter:
    """Streams chunks into a new tile store folder; :meth:`close` seals it.

    The store is written into a hidden sibling folder and renamed into place when sealed,
    so an error or Ctrl-C leaves nothing under ``directory`` (use as a context manager).
    Without a ``directory`` the store is temporary: held in memory when no tile had to be
    spilled to disk, else sealed in a scratch folder under ``workdir`` that the caller removes
    (:class:`TemporaryTileStore` does both).

    Args:
        directory: the store folder to create, or None for a temporary store.
        grid: the tiles.
        subdivisions: sub-cells per tile edge of the spatial index.
        buffer_points: points held in memory before appending to the tile files.
        overwrite: replace an existing store folder at ``directory``.
        workdir: where a temporary store spills (the system's temporary folder by default).
        metadata: JSON-ready values kept in the manifest (e.g. what the store was built from).
    """

    def __init__(
        self,
        directory: str | Path | None,
        *,
        grid: TileGrid,
        subdivisions: int = DEFAULT_SUBDIVISIONS,
        buffer_points: int = DEFAULT_BUFFER_POINTS,
        overwrite: bool = False,
        metadata: dict[str, Any] | None = None,
        workdir: str | Path | None = None,
    ) -> None:
        self.directory = None if directory is None else Path(directory)
        if self.directory is not None and self.directory.exists() and not overwrite:
            raise FileExistsError(
                f"{self.directory}: expected a new folder for the tile store, found one "
                "(pass overwrite=True to replace it)"
            )
        if not 1 <= subdivisions <= 256:
            raise ShapeError(f"subdivisions: expected 1..256, found {subdivisions}")
        self.grid = grid
        self.subdivisions = subdivisions
        self.metadata = dict(metadata or {})
        self._buffer_points = buffer_points
        if self.directory is None:
            self._staging = Path(tempfile.mkdtemp(prefix="semantic3d-tiles-", dir=workdir))
        else:
            self.directory.parent.mkdir(parents=True, exist_ok=True)
            self._staging = self.directory.with_name(
                f".{self.directory.name}.{uuid.uuid4().hex[:8]}.partial"
            )
            self._staging.mkdir()
        self._buffers: dict[TileKey, list[NDArray[Any]]] = defaultdict(list)
        self._buffered = 0
        self._on_disk: set[TileKey] = set()
        self._dtype: np.dtype[Any] | None = None
        self.n_points = 0
        """Points stored so far."""
        self._next_index = 0
        self.spilled_points = 0

    def __enter__(self) -> TileStoreWriter:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        if exc_type is not None:
            self.abort()

    def add(
        self,
        cloud: PointCloud,
        *,
        indices: NDArray[np.int64] | None = None,
        keep: NDArray[np.bool_] | None = None,
    ) -> None:
        """Bin the points of ``cloud``.

        Args:
            cloud: the next chunk (every chunk with labels, or none).
            indices: position of each point in the scan; default: the running count
                (which counts every point of every chunk, kept or not).
            keep: store only these points (cheaper than filtering the chunk first).
        """
        if self._dtype is None:
            self._dtype = record_dtype(with_labels=cloud.labels is not None)
        elif (cloud.labels is not None) != ("labels" in (self._dtype.names or ())):
            raise ShapeError("chunks: expected labels on every chunk or on none")
        n = cloud.n_points
        if indices is not None and np.shape(indices) != (n,):
            raise ShapeError(f"indices: expected ({n},), found {np.shape(indices)}")
        if keep is not None and np.shape(keep) != (n,):
            raise ShapeError(f"keep: expected ({n},), found {np.shape(keep)}")
        if n == 0:
            return
        # one pass on every thread: keys, the kept keys' extent, the coordinates checked
        keys, extent = self.grid.tile_keys_extent(cloud.xyz, keep=keep)
        if indices is None:
            indices = np.arange(self._next_index, self._next_index + n, dtype=np.int64)
        if extent is not None:
            self._add_grouped(keys, extent, cloud, np.asarray(indices, np.int64), keep)
        self._next_index += n

    def _add_grouped(
        self,
        keys: NDArray[np.int64],
        extent: tuple[int, int, int, int],
        cloud: PointCloud,
        indices: NDArray[np.int64],
        keep: NDArray[np.bool_] | None,
    ) -> None:
        # Number the chunk's tiles densely, then one counting sort (compiled) writes the
        # records grouped by tile, scan order inside a tile. Dropped points get the last
        # id and are left out.
        import numba

        from semantic3d.spatial._kernels import extent_slots, group_by_slot

        x0, x1, y0, y1 = extent
        nx, ny = x1 - x0 + 1, y1 - y0 + 1
        if max(nx, ny) > _MAX_TILE_SPAN:
            raise ShapeError(
                f"xyz: expected points within {_MAX_TILE_SPAN} tiles of one another along x "
                f"and y, found tiles {x0}..{x1} by {y0}..{y1}"
            )
        marks = np.empty(0, np.bool_) if keep is None else np.ascontiguousarray(keep, np.bool_)
        n_slots = nx * ny
        dense = extent_slots(keys, x0, y0, ny, marks, n_slots)
        n_kept = cloud.n_points if keep is None else int(np.count_nonzero(keep))
        cells = None
        if n_slots > max(np.iinfo(np.uint16).max - 1, 4 * n_kept):  # sparse tiles: renumber
            kept = dense if keep is None else dense[keep]
            cells, numbers = np.unique(kept, return_inverse=True)
            n_slots = cells.size
            if keep is None:
                dense = numbers.reshape(-1)
            else:
                dense = np.full(cloud.n_points, n_slots, dtype=np.int64)  # dropped: the last id
                dense[keep] = numbers.reshape(-1)
        assert self._dtype is not None
        grouped = np.empty(n_kept, self._dtype)
        labels = cloud.labels
        no_labels = np.empty(0, np.uint8)
        counts = group_by_slot(
            np.ascontiguousarray(dense, np.int64),
            n_slots,
            cloud.xyz,
            indices,
            cloud.intensity,
            cloud.rgb,
            no_labels if labels is None else labels,
            grouped["xyz"],
            grouped["index"],
            grouped["intensity"],
            grouped["rgb"],
            no_labels if labels is None else grouped["labels"],
            numba.get_num_threads(),
        )
        ends = np.cumsum(counts)
        for slot in np.flatnonzero(counts).tolist():
            cell = slot if cells is None else int(cells[slot])
            tile = (x0 + cell // ny, y0 + cell % ny)
            begin, end = int(ends[slot] - counts[slot]), int(ends[slot])
            self._buffers[tile].append(grouped[begin:end])
        self._buffered += n_kept
        self.n_points += n_kept
        if self._buffered > self._buffer_points:
            self._flush()

    def _part(self, tile: TileKey) -> Path:
        return self._staging / f"{tile[0]}_{tile[1]}.part"

    def _flush(self) -> None:
        """Append every buffered tile to its part file: tiles at the same time on the
        thread budget's threads, the largest first (writes to one file take turns, to
        different files they do not: the stream's binning waited for them on one
        thread)."""
        held = sorted(
            self._buffers.items(),
            key=lambda item: (-sum(part.shape[0] for part in item[1]), item[0]),
        )

        def append(item: tuple[TileKey, list[NDArray[Any]]]) -> tuple[TileKey, int]:
            tile, parts = item
            with self._part(tile).open("ab") as handle:
                for part in parts:
                    part.tofile(handle)
            return tile, sum(part.shape[0] for part in parts)

        for tile, n_points in map_in_threads(
            append, held, n_threads=thread_budget(), ordered=False, name="s3d-spill"
        ):
            self.spilled_points += n_points
            self._on_disk.add(tile)
        self._buffers.clear()
        self._buffered = 0

    def close(self) -> TileStore:
        """Seal every tile (spatial index), write the manifest and move the folder in place."""
        try:
            return self._seal()
        except BaseException:
            self.abort()
            raise

    def _seal(self) -> TileStore:
        dtype = self._dtype if self._dtype is not None else record_dtype(with_labels=False)
        tiles = sorted(set(self._buffers) | self._on_disk)
        n_cells = self.subdivisions**2
        offsets = np.zeros((len(tiles), n_cells + 1), np.int64)
        starts = np.zeros(len(tiles) + 1, np.int64)
        counts = [self._count(tile, dtype) for tile in tiles]
        np.cumsum(counts, out=starts[1:])
        if self.directory is None and not self._on_disk:
            points = np.empty(self.n_points, dtype)
            order = np.empty(self.n_points, np.int32)

            def fill(row: int) -> None:
                begin, end = int(starts[row]), int(starts[row + 1])
                self._fill(tiles[row], points[begin:end], order[begin:end], offsets[row])

            self._each_tile(fill, counts)
            shutil.rmtree(self._staging, ignore_errors=True)
            return TileStore._in_memory(
                grid=self.grid,
                subdivisions=self.subdivisions,
                tiles=tiles,
                offsets=offsets,
                starts=starts,
                points=points,
                order=order,
                metadata=self.metadata,
            )
        self._write(tiles, dtype, offsets, starts, counts)
        np.save(self._staging / KEYS_FILE, np.array(tiles, dtype=np.int64).reshape(-1, 2))
        np.save(self._staging / OFFSETS_FILE, offsets)
        np.save(self._staging / STARTS_FILE, starts)
        manifest = {
            "version": STORE_VERSION,
            "grid": self.grid.to_dict(),
            "subdivisions": self.subdivisions,
            "n_points": self.n_points,
            "has_labels": "labels" in (dtype.names or ()),
            "metadata": self.metadata,
        }
        (self._staging / MANIFEST_FILE).write_text(json.dumps(manifest, indent=1), encoding="utf-8")
        final = self._staging if self.directory is None else self.directory
        if final != self._staging:
            if final.exists():
                shutil.rmtree(final)
            self._staging.rename(final)
        logger.info("tiled %d points into %d tiles", self.n_points, len(tiles))
        return TileStore(final)

    def _count(self, tile: TileKey, dtype: np.dtype[Any]) -> int:
        """Points of ``tile`` held in memory and spilled to its file."""
        count = sum(part.shape[0] for part in self._buffers.get(tile, []))
        if tile in self._on_disk:
            count += self._part(tile).stat().st_size // dtype.itemsize
        return count

    @staticmethod
    def _each_tile(function: Callable[[int], None], counts: list[int]) -> None:
        """``function(row)`` for every tile, tiles at the same time on the thread budget's
        threads, the largest first, each tile's kernels on a share of the threads in
        proportion to its points (the densest tile of a scan holds half of them)."""
        n_threads = thread_budget()
        total = max(1, sum(counts))
        rows = sorted(range(len(counts)), key=lambda row: (-counts[row], row))
        for _ in map_in_threads(
            function,
            rows,
            n_threads=n_threads,
            ordered=False,
            numba_threads_per_task=lambda row: max(1, round(n_threads * counts[row] / total)),
            name="s3d-seal",
        ):
            pass

    def _fill(
        self,
        tile: TileKey,
        records: NDArray[Any],
        order: NDArray[np.int32],
        offsets: NDArray[np.int64],
    ) -> None:
        """Write ``tile``'s records held in memory (a store with no tile spilled) into
        ``records`` and its sub-cell index into ``order`` and ``offsets``."""
        end = 0
        for part in self._buffers.pop(tile, []):  # as bytes: a structured copy is ~8x slower
            _as_bytes(records[end : end + part.shape[0]])[...] = _as_bytes(part)
            end += part.shape[0]
        codes = np.empty(records.shape[0], np.uint16)
        self._code(tile, records, codes)
        self._order(codes, order, offsets)

    def _code(self, tile: TileKey, records: NDArray[Any], codes: NDArray[np.uint16]) -> None:
        """The sub-cell of each of ``records`` (points of ``tile``) into ``codes``."""
        from semantic3d.spatial._kernels import sub_cell_codes

        t_x0, t_y0, _, _ = self.grid.tile_bounds(tile)
        sub_cell_codes(
            records["xyz"],
            t_x0,
            t_y0,
            self.grid.tile_size_m / self.subdivisions,
            self.subdivisions,
            codes,
        )

    def _order(
        self, codes: NDArray[np.uint16], order: NDArray[np.int32], offsets: NDArray[np.int64]
    ) -> None:
        """A tile's points sub-cell by sub-cell (a stable counting sort of their codes)."""
        import numba

        from semantic3d.spatial._kernels import order_by_code

        order_by_code(codes, self.subdivisions**2, order, offsets, numba.get_num_threads())

    def _windows(
        self, tile: TileKey, dtype: np.dtype[Any], window: NDArray[Any]
    ) -> Iterator[NDArray[Any]]:
        """``tile``'s records in their order, a window at a time: its spilled ones read
        into ``window`` (reused: each is valid until the next), then those in memory."""
        if tile in self._on_disk:
            path = self._part(tile)
            with path.open("rb") as stream:
                size = os.fstat(stream.fileno()).st_size
                if size % dtype.itemsize:
                    raise DataFormatError(
                        f"{path}: expected whole records of {dtype.itemsize} bytes, "
                        f"found {size} bytes"
                    )
                left = size // dtype.itemsize
                while left:
                    records = window[: min(left, window.shape[0])]
                    view = _as_bytes(records).data.cast("B")
                    got = 0
                    while got < view.nbytes:  # short reads: read on
                        read = stream.readinto(view[got:])
                        if not read:
                            raise DataFormatError(
                                f"{path}: expected {size} bytes, found {stream.tell()}"
                            )
                        got += read
                    left -= records.shape[0]
                    yield records
        yield from self._buffers.pop(tile, [])

    def _write(
        self,
        tiles: list[TileKey],
        dtype: np.dtype[Any],
        offsets: NDArray[np.int64],
        starts: NDArray[np.int64],
        counts: list[int],
    ) -> None:
        """Write the point and order files, each tile at its place with positioned writes
        (tiles at the same time), a window of its records at a time: a tile being sealed
        holds 6 bytes a point (its sub-cell codes and order) and one window, not its
        44-byte records (the densest tile of a station holds over half of its points). A
        file written through a memory map would count every page it wrote in the
        process's resident memory, the whole store at the end."""
        with (
            (self._staging / POINTS_FILE).open("wb") as points_file,
            (self._staging / ORDER_FILE).open("wb") as order_file,
        ):
            _write_npy_header(points_file, dtype, self.n_points)
            _write_npy_header(order_file, np.dtype(np.int32), self.n_points)
            points_file.flush()
            order_file.flush()
            points_at, order_at = points_file.tell(), order_file.tell()
            writing = threading.Lock()

            def write(row: int) -> None:
                tile, begin = tiles[row], int(starts[row])
                codes = np.empty(counts[row], np.uint16)
                window = np.empty(min(counts[row], _SEAL_WINDOW), dtype)
                at = 0
                for records in self._windows(tile, dtype, window):
                    self._code(tile, records, codes[at : at + records.shape[0]])
                    # one writer at a time (a file's writes take turns anyway), on one
                    # thread: the task's other threads go back to the map meanwhile
                    with serial_section(), writing:
                        _write_at(
                            points_file.fileno(),
                            _as_bytes(records),
                            points_at + (begin + at) * dtype.itemsize,
                        )
                    at += records.shape[0]
                if at != counts[row]:
                    raise DataFormatError(
                        f"{self._part(tile)}: expected {counts[row]} points of tile {tile}, "
                        f"found {at}"
                    )
                del window
                order = np.empty(counts[row], np.int32)
                self._order(codes, order, offsets[row])
                del codes
                with serial_section(), writing:
                    _write_at(order_file.fileno(), order, order_at + begin * order.itemsize)
                self._part(tile).unlink(missing_ok=True)

            self._each_tile(write, counts)

    def abort(self) -> None:
        """Remove everything written; ``directory`` is left as it was."""
        self._buffers.clear()
        shutil.rmtree(self._staging, ignore_errors=True)


def build_tile_store(
    chunks: Iterable[PointCloud],
    directory: str | Path,
    *,
    grid: TileGrid,
    subdivisions: int = DEFAULT_SUBDIVISIONS,
    buffer_points: int = DEFAULT_BUFFER_POINTS,
    overwrite: bool = False,
    metadata: dict[str, Any] | None = None,
) -> TileStore:
    """Stream ``chunks`` once into a new tile store at ``directory`` (see the module docs).

    Raises:
        FileExistsError: ``directory`` exists and ``overwrite`` is False.
        ShapeError: labels on some chunks only.
    """
    with TileStoreWriter(
        directory,
        grid=grid,
        subdivisions=subdivisions,
        buffer_points=buffer_points,
        overwrite=overwrite,
        metadata=metadata,
    ) as writer:
        for chunk in chunks:
            writer.add(chunk)
        return writer.close()


class TemporaryTileStore:
    """A tile store for one process, removed on exit: in memory when it fits the buffer.

    >>> from semantic3d.core.pointcloud import PointCloud
    >>> cloud = PointCloud.from_arrays(np.array([[0.5, 0.5, 0.0], [1.5, 0.2, 0.0]]))
    >>> with TemporaryTileStore([cloud], grid=TileGrid.square(1.0)) as store:
    ...     store.tiles, store.read_halo((0, 0), 0.6).indices.tolist()
    (((0, 0), (1, 0)), [1])
    """

    def __init__(
        self,
        chunks: Iterable[PointCloud],
        *,
        grid: TileGrid,
        workdir: str | Path | None = None,
        subdivisions: int = DEFAULT_SUBDIVISIONS,
        buffer_points: int = DEFAULT_BUFFER_POINTS,
    ) -> None:
        with TemporaryTileStore.writer(
            grid=grid, workdir=workdir, subdivisions=subdivisions, buffer_points=buffer_points
        ) as writer:
            for chunk in chunks:
                writer.add(chunk)
            self.store = writer.close()
        self.spilled_points = writer.spilled_points

    @staticmethod
    def writer(
        *,
        grid: TileGrid,
        workdir: str | Path | None = None,
        subdivisions: int = DEFAULT_SUBDIVISIONS,
        buffer_points: int = DEFAULT_BUFFER_POINTS,
    ) -> TileStoreWriter:
        """A writer of a temporary store, for callers that bin chunks themselves.

        Wrap what its ``close()`` returns in :meth:`adopt` so that it is removed.
        """
        if workdir is not None:
            Path(workdir).mkdir(parents=True, exist_ok=True)
        return TileStoreWriter(
            None, grid=grid, subdivisions=subdivisions, buffer_points=buffer_points, workdir=workdir
        )

    @classmethod
    def adopt(cls, store: TileStore, *, spilled_points: int = 0) -> TemporaryTileStore:
        """Own ``store`` (from :meth:`writer`): it is removed when the context exits."""
        temporary = cls.__new__(cls)
        temporary.store = store
        temporary.spilled_points = spilled_points
        return temporary

    def __enter__(self) -> TileStore:
        return self.store

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.close()

    def close(self) -> None:
        """Remove the store's scratch folder, if it has one."""
        if self.store.directory is not None:
            shutil.rmtree(self.store.directory, ignore_errors=True)
