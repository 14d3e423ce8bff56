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
``buffer_points``; while reading, by the tiles read.
"""

from __future__ import annotations

import json
import logging
import math
import shutil
import tempfile
import uuid
from collections import defaultdict
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from semantic3d.core.errors import DataFormatError, ShapeError
from semantic3d.core.pointcloud import PointCloud
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
DEFAULT_SUBDIVISIONS = 16
DEFAULT_BUFFER_POINTS = 1 << 22
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
        """Points of packed records (copied out of any memory map)."""
        labels = (
            np.ascontiguousarray(records["labels"])
            if "labels" in (records.dtype.names or ())
            else None
        )
        cloud = PointCloud(
            np.ascontiguousarray(records["xyz"]),
            np.ascontiguousarray(records["intensity"]),
            np.ascontiguousarray(records["rgb"]),
            labels,
        )
        return cls(cloud, np.ascontiguousarray(records["index"]))


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
        if self._starts.shape != (len(self.tiles) + 1,) or int(self._starts[-1]) != self.n_points:
            raise DataFormatError(
                f"expected {self.n_points} points in {len(self.tiles)} tiles, found an index "
                "that disagrees",
                path=str(self.directory),
            )

    def _arrays(self) -> tuple[NDArray[Any], NDArray[np.int32]]:
        """The memory maps of the points and of the sub-cell order, opened once."""
        if self._points is None or self._order is None:
            try:
                # Plain arrays over the maps: slicing a np.memmap subclass costs ~10 µs.
                self._points = np.asarray(np.load(self.directory / POINTS_FILE, mmap_mode="r"))
                self._order = np.asarray(np.load(self.directory / ORDER_FILE, mmap_mode="r"))
            except (OSError, ValueError) as exc:
                raise DataFormatError(
                    f"expected the store's point files, found {exc}", path=str(self.directory)
                ) from exc
            if self._points.shape != (self.n_points,) or self._points.dtype != self._dtype:
                raise DataFormatError(
                    f"expected {self.n_points} records of {self._dtype}, found "
                    f"{self._points.shape} {self._points.dtype}",
                    path=str(self.directory / POINTS_FILE),
                )
        return self._points, self._order

    def __reduce__(self) -> tuple[Any, tuple[str]]:
        return (TileStore, (str(self.directory),))

    def __repr__(self) -> str:
        return (
            f"TileStore({str(self.directory)!r}, {len(self.tiles)} tiles, {self.n_points} points)"
        )

    def __contains__(self, tile: object) -> bool:
        return tile in self._row

    def count(self, tile: TileKey) -> int:
        """Points in ``tile`` (0 for an empty tile)."""
        row = self._row.get(tile)
        return 0 if row is None else int(self._starts[row + 1] - self._starts[row])

    @property
    def tile_size_m(self) -> float:
        """Edge of a tile."""
        return self.grid.tile_size_m

    def _records(self, tile: TileKey) -> tuple[NDArray[Any], NDArray[np.int32]]:
        """Memory-mapped records of ``tile`` and their sub-cell order (local indices)."""
        row = self._row[tile]
        begin, end = int(self._starts[row]), int(self._starts[row + 1])
        points, order = self._arrays()
        return points[begin:end], order[begin:end]

    def read_core(self, tile: TileKey) -> TilePoints:
        """The points of ``tile`` in the order they were streamed (empty for an empty tile)."""
        if tile not in self._row:
            return TilePoints.from_records(np.empty(0, self._dtype))
        return TilePoints.from_records(self._records(tile)[0])

    def read_halo(self, tile: TileKey, halo_m: float) -> TilePoints:
        """Points of the other tiles within ``halo_m`` of ``tile``'s rectangle (edges included).

        Neighbour by neighbour, in tile order; inside a neighbour, sub-cell by sub-cell.
        """
        if not (math.isfinite(halo_m) and halo_m >= 0):
            raise ShapeError(f"halo_m: expected a finite width >= 0, found {halo_m}")
        parts = [
            part
            for other, box in self._halo_boxes(tile, halo_m)
            if (part := self._read_box(other, box)).size
        ]
        if not parts:
            return TilePoints.from_records(np.empty(0, self._dtype))
        return TilePoints.from_records(parts[0] if len(parts) == 1 else np.concatenate(parts))

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
        x_min, y_min, x_max, y_max = box
        size = self.grid.tile_size_m
        x0, y0 = self.grid.origin_xy
        low = (math.floor((x_min - x0) / size) - 1, math.floor((y_min - y0) / size) - 1)
        high = (math.floor((x_max - x0) / size) + 1, math.floor((y_max - y0) / size) + 1)
        parts = [
            part
            for other in self.tiles
            if low[0] <= other[0] <= high[0] and low[1] <= other[1] <= high[1]
            if (part := self._read_box(other, box)).size
        ]
        if not parts:
            return TilePoints.from_records(np.empty(0, self._dtype))
        return TilePoints.from_records(parts[0] if len(parts) == 1 else np.concatenate(parts))

    def jobs(self, *, halo_m: float = 0.0) -> tuple[TileJob, ...]:
        """One picklable job per non-empty tile, in tile order."""
        from semantic3d.spatial.job import TileJob

        return tuple(
            TileJob(str(self.directory), tile, self.grid.tile_bounds(tile), halo_m)
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

    def _read_box(self, tile: TileKey, box: Bounds) -> NDArray[Any]:
        """Records of ``tile`` inside ``box``, through the sub-cell index."""
        row = self._row[tile]
        offsets = self._offsets[row]
        n_sub = self.subdivisions
        t_x0, t_y0, _, _ = self.grid.tile_bounds(tile)
        sub = self.grid.tile_size_m / n_sub

        def span(low: float, high: float, start: float) -> tuple[int, int]:
            # One sub-cell of slack each side absorbs rounding in the sub-cell assignment.
            first = max(0, math.floor((low - start) / sub) - 1)
            last = min(n_sub - 1, math.floor((high - start) / sub) + 1)
            return first, last

        sx0, sx1 = span(box[0], box[2], t_x0)
        sy0, sy1 = span(box[1], box[3], t_y0)
        if sx0 > sx1 or sy0 > sy1:
            return np.empty(0, self._dtype)
        records, order = self._records(tile)
        whole = sx0 == 0 and sy0 == 0 and sx1 == n_sub - 1 and sy1 == n_sub - 1
        if whole or records.shape[0] <= _SMALL_TILE_POINTS:
            candidates = np.asarray(records)
        else:
            rows = [
                order[offsets[sx * n_sub + sy0] : offsets[sx * n_sub + sy1 + 1]]
                for sx in range(sx0, sx1 + 1)
            ]
            picked = np.concatenate(rows) if len(rows) > 1 else np.asarray(rows[0])
            if picked.size == 0:
                return np.empty(0, self._dtype)
            candidates = records[np.sort(picked)]
        xyz = candidates["xyz"]
        inside = (
            (xyz[:, 0] >= box[0])
            & (xyz[:, 0] <= box[2])
            & (xyz[:, 1] >= box[1])
            & (xyz[:, 1] <= box[3])
        )
        selected: NDArray[Any] = candidates[inside]
        return selected


class TileStoreWriter:
    """Streams chunks into a new tile store folder; :meth:`close` seals it.

    The store is written into a hidden sibling folder and renamed into place when sealed,
    so an error or Ctrl-C leaves nothing under ``directory`` (use as a context manager).

    Args:
        directory: the store folder to create.
        grid: the tiles.
        subdivisions: sub-cells per tile edge of the spatial index.
        buffer_points: points held in memory before appending to the tile files.
        overwrite: replace an existing store folder at ``directory``.
        metadata: JSON-ready values kept in the manifest (e.g. what the store was built from).
    """

    def __init__(
        self,
        directory: str | Path,
        *,
        grid: TileGrid,
        subdivisions: int = DEFAULT_SUBDIVISIONS,
        buffer_points: int = DEFAULT_BUFFER_POINTS,
        overwrite: bool = False,
        metadata: dict[str, Any] | None = None,
    ) -> None:
        self.directory = Path(directory)
        if self.directory.exists() and not overwrite:
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

    def add(self, cloud: PointCloud, *, indices: NDArray[np.int64] | None = None) -> None:
        """Bin the points of ``cloud``.

        Args:
            cloud: the next chunk (every chunk with labels, or none).
            indices: position of each point in the scan; default: the running count.
        """
        if self._dtype is None:
            self._dtype = record_dtype(with_labels=cloud.labels is not None)
        elif (cloud.labels is not None) != ("labels" in (self._dtype.names or ())):
            raise ShapeError("chunks: expected labels on every chunk or on none")
        n = cloud.n_points
        if indices is not None and np.shape(indices) != (n,):
            raise ShapeError(f"indices: expected ({n},), found {np.shape(indices)}")
        if n == 0:
            return
        records = np.empty(n, self._dtype)
        records["xyz"] = cloud.xyz
        records["index"] = (
            np.arange(self.n_points, self.n_points + n, dtype=np.int64)
            if indices is None
            else indices
        )
        records["intensity"] = cloud.intensity
        records["rgb"] = cloud.rgb
        if cloud.labels is not None:
            records["labels"] = cloud.labels
        if not np.all(np.isfinite(cloud.xyz[:, :2])):
            raise ShapeError("xyz: expected finite coordinates, found NaN or infinity")
        keys = self.grid.tile_keys(cloud.xyz)
        self._add_grouped(keys[:, 0], keys[:, 1], records)
        self.n_points += n

    def _add_grouped(
        self, ix: NDArray[np.int64], iy: NDArray[np.int64], records: NDArray[Any]
    ) -> None:
        # Group by tile with one sort of a dense tile id: a stable sort of uint16 keys is a
        # radix sort in numpy (linear time), the common case for one chunk. Stable, so each
        # tile keeps the stream's order.
        x0, y0 = int(ix.min()), int(iy.min())
        nx, ny = int(ix.max()) - x0 + 1, int(iy.max()) - y0 + 1
        dense = (ix - x0) * ny + (iy - y0)
        cells = None
        if nx * ny > max(np.iinfo(np.uint16).max, 4 * ix.shape[0]):
            cells, dense = np.unique(dense, return_inverse=True)  # sparse tiles: renumber
            dense = dense.reshape(-1)
        if int(dense.max()) <= np.iinfo(np.uint16).max:
            dense = dense.astype(np.uint16)
        order = np.argsort(dense, kind="stable")
        counts = np.bincount(dense)
        ends = np.cumsum(counts)
        grouped = records[order]
        for slot in np.flatnonzero(counts).tolist():
            cell = slot if cells is None else int(cells[slot])
            tile = (x0 + cell // ny, y0 + cell % ny)
            begin, end = int(ends[slot] - counts[slot]), int(ends[slot])
            self._buffers[tile].append(grouped[begin:end])
        self._buffered += records.shape[0]
        if self._buffered > self._buffer_points:
            self._flush()

    def _part(self, tile: TileKey) -> Path:
        return self._staging / f"{tile[0]}_{tile[1]}.part"

    def _flush(self) -> None:
        for tile, parts in self._buffers.items():
            with self._part(tile).open("ab") as handle:
                for part in parts:
                    part.tofile(handle)
                    self.spilled_points += part.shape[0]
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
        points = np.lib.format.open_memmap(
            self._staging / POINTS_FILE, mode="w+", dtype=dtype, shape=(self.n_points,)
        )
        order = np.lib.format.open_memmap(
            self._staging / ORDER_FILE, mode="w+", dtype=np.int32, shape=(self.n_points,)
        )
        try:
            begin = 0
            for row, tile in enumerate(tiles):
                parts: list[NDArray[Any]] = []
                if tile in self._on_disk:
                    parts.append(np.fromfile(self._part(tile), dtype))
                parts.extend(self._buffers.pop(tile, []))
                records = parts[0] if len(parts) == 1 else np.concatenate(parts)
                end = begin + records.shape[0]
                sub = self._sub_cells(tile, records["xyz"])
                points[begin:end] = records
                order[begin:end] = np.argsort(sub, kind="stable")
                offsets[row, 1:] = np.cumsum(np.bincount(sub, minlength=n_cells))
                starts[row + 1] = end
                self._part(tile).unlink(missing_ok=True)
                begin = end
            points.flush()
            order.flush()
        finally:
            del points, order  # close the maps before the folder is renamed
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
        if self.directory.exists():
            shutil.rmtree(self.directory)
        self._staging.rename(self.directory)
        logger.info("tiled %d points into %d tiles", self.n_points, len(tiles))
        return TileStore(self.directory)

    def _sub_cells(self, tile: TileKey, xyz: NDArray[np.float64]) -> NDArray[np.intp]:
        n_sub = self.subdivisions
        t_x0, t_y0, _, _ = self.grid.tile_bounds(tile)
        sub = self.grid.tile_size_m / n_sub
        sx = np.clip(np.floor((xyz[:, 0] - t_x0) / sub), 0, n_sub - 1).astype(np.intp)
        sy = np.clip(np.floor((xyz[:, 1] - t_y0) / sub), 0, n_sub - 1).astype(np.intp)
        cells: NDArray[np.intp] = sx * n_sub + sy
        return cells

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
    """A tile store in a scratch folder, removed on exit.

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
        if workdir is not None:
            Path(workdir).mkdir(parents=True, exist_ok=True)
        self._scratch = Path(tempfile.mkdtemp(prefix="semantic3d-tiles-", dir=workdir))
        try:
            self.store = build_tile_store(
                chunks,
                self._scratch / "store",
                grid=grid,
                subdivisions=subdivisions,
                buffer_points=buffer_points,
            )
        except BaseException:
            shutil.rmtree(self._scratch, ignore_errors=True)
            raise

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
        """Remove the scratch folder."""
        shutil.rmtree(self._scratch, ignore_errors=True)
