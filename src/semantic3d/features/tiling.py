"""Multi-scale features of scans larger than memory, tile by tile, equal to the whole-scan rows.

:class:`TiledScan` streams point chunks once into a tile store
(:mod:`semantic3d.spatial.store`), then builds each tile's voxel pyramid, then computes
features tile by tile. Tiles are made of whole voxels of the coarsest level (a
:class:`~semantic3d.spatial.grid.TileGrid` of base-voxel cells), so every voxel of every
level lies in exactly one tile and each tile's pyramid holds exactly the whole scan's
voxels. At level ``l`` a tile's queries look for neighbours among the level-``l`` points
of the tile plus a *halo* gathered from its neighbours. The halo is per level (fine levels
need centimetres, coarse ones metres) and adaptive: a query is accepted only when its k-th
neighbour (and its cylinder's radius) is closer than the halo's edge (so no point outside
could change its row); the others are asked again in a box holding the ball of their
k-th distance. The first halo of a
level is estimated once, from the densest tile, so every tile is computed the same way
whatever the order tiles are visited in. In voxel mode the coarsest levels, which hold
few voxels, are described once over the whole scan instead. With the canonical neighbour
order of :mod:`~semantic3d.features.neighbourhoods`, rows are bit-for-bit those of
:func:`~semantic3d.features.multiscale.compute_multiscale_features`.

Peak memory is set by the tiles described at once (the largest, as many as the threads
allow) and their halos: their level voxels, and about 17 bytes a point of theirs (scan
positions, point-to-voxel map, labels). A tile's pyramid is built
:data:`PYRAMID_PART_POINTS` points at a time and its points' positions are copied only
when asked for, so the densest tile of a scan, which grows with the scan, holds no more;
disk use is about 44 bytes per point plus the pyramids.
"""

from __future__ import annotations

import logging
import math
import pickle
import shutil
import tempfile
import threading
from collections import OrderedDict
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from itertools import chain, pairwise
from pathlib import Path
from types import TracebackType
from typing import TypeVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from semantic3d.core.errors import ShapeError
from semantic3d.core.pointcloud import PointCloud
from semantic3d.core.threads import (
    apportion_threads,
    enclosing_map_threads,
    iter_ahead,
    map_in_threads,
    serial_section,
    take_free_threads,
    thread_budget,
)
from semantic3d.core.timeline import span
from semantic3d.features._row_kernels import (
    exact_rows,
    put_rows,
    put_values,
    rows_in_box,
    rows_of_keys,
    scatter_rows,
    store_keys,
    take_rows,
)
from semantic3d.features.config import ConfigError, FeatureConfig
from semantic3d.features.multiscale import (
    FeatureTable,
    RowMap,
    attribute_columns,
    compute_level_features,
    distinct_voxels,
    level_reach,
    level_rows,
    map_rows,
    map_table_rows,
    reach_of_kth,
)
from semantic3d.features.neighbourhoods import LevelIndex, kth_squared_distances
from semantic3d.features.pyramid import build_pyramid, build_pyramid_in_parts, grid_origin
from semantic3d.spatial.grid import TileGrid, TileKey
from semantic3d.spatial.store import TilePoints, TileStore, build_tile_store
from semantic3d.spatial.voxels import CELL_BITS, CELL_OFFSET

logger = logging.getLogger(__name__)

DEFAULT_TILE_SIZE_M = 25.6
"""Default tile edge (rounded up to a multiple of the coarsest voxel)."""

_SAFETY_M = 1e-3
"""Margin kept between a k-th neighbour and the halo edge (covers the float32 search)."""

_FIRST_HALO_VOXELS = 4.0
"""First halo of a level, in voxels of that level (k = 10 on a surface needs ~2)."""

_WHOLE_VOXEL_COST = 12
"""A voxel described whole (its k-NN query, features and cylinders) costs about this many
voxels of a first halo's tree build (measured on simulated street scans: 2.9 µs against
0.23 µs a voxel on one thread); it only shares threads out, never changes a row."""

_POINT_WORK_VOXELS = 0.025
"""A tile's work, in level-0 voxels: its level-0 voxels plus this many a point. A tile's
levels, forest rows and graph grow with its voxels, not its points: on one thread, a
10 M-point street scan's densest tile held 68 % of the points and 40 % of the time, and
level-0 voxels plus 1/40 a point gave each of its large tiles' time within 15 % (points
alone: off by up to 70 %). It only shares threads out among tiles, never changes a row."""

PYRAMID_PART_POINTS = 1 << 21
"""A tile of more points builds its pyramid this many points at a time
(:func:`~semantic3d.features.pyramid.build_pyramid_in_parts`: the same pyramid, ~110
bytes a point of the part held instead of the tile's; the densest tile grows with the
scan: 68 % of a 10 M-point street scan's points)."""

_PARTS_PER_THREAD = 4
"""A large tile level's queries are computed in up to this many parts a thread."""

_MIN_PART_QUERIES = 10_000
"""The fewest queries a part holds (a part builds its own k-d tree over its box)."""

_GROWING_MAP_THREADS = 4
"""A tile on one thread of a map of at least this many threads computes its large levels
in parts too (:data:`_GROWING_PARTS`): the parts then go on with the threads other tiles
leave (the nested map grows), instead of one thread doing the level alone while they idle.
Below it the parts' halos would cost more than the few threads they could gain."""

_GROWING_PARTS = 4
"""Parts of a large level of a tile on one thread of a large map: computed one after
another on one thread, 4 parts a level cost what one piece does (a tile of 335 k level-0
voxels: 8 parts +3-18 %, 16 parts +20-32 %), and they can run on 4 threads once other
tiles leave them."""

_COST_CELL_RADII = 4.0
"""A part's work is estimated from the level's points per square this many cylinder radii
wide around each query (:func:`part_blocks`)."""

_QUERY_COST_POINTS = 1000.0
"""A query's own cost (its k-NN search), in points of its square's count: fitted to the
parts' CPU time in a 10 M-point street scan's densest tile (levels 0-2 alike)."""

_BOUND_SAMPLE = 1 << 14
"""Queries sampled to place the parts' bounds."""

_BRUTE_FORCE_PAIRS = 1 << 26
"""Query-point pairs up to which a bound on the k-th distance scans every point (a few
queries: milliseconds) rather than building a k-d tree (:meth:`TiledScan._reach_bound`)."""

_SIDE_PIECES = 4
"""The queries a first ask leaves are asked again in this many boxes a side of it."""

_SLACK_M = 1e-6
"""Points may sit this far outside their tile's edges (rounding of cell indices)."""

_HALO_SAMPLE = 2048
"""Queries of the densest tile used to estimate a level's first halo."""

_SHARED_FILE = "shared.pickle"
"""What :meth:`TiledScan.share` writes in the scratch folder."""

Tile = TileKey
R = TypeVar("R")


@dataclass(frozen=True, slots=True)
class _TileLevel:
    """What the feature pass reads of a pyramid level (no integer cells: 40% smaller)."""

    xyz: NDArray[np.float64]
    keys: NDArray[np.int64]
    attributes: NDArray[np.float64]
    parent: NDArray[np.int64]

    @property
    def n_voxels(self) -> int:
        return int(self.keys.shape[0])

    @property
    def nbytes(self) -> int:
        return self.xyz.nbytes + self.keys.nbytes + self.attributes.nbytes + self.parent.nbytes


@dataclass(frozen=True, slots=True)
class _WholeLevel:
    """A level described whole (:meth:`TiledScan._whole_level`): its sorted keys, their
    feature rows and, for level 0, the keys of every voxel's k nearest (else None)."""

    keys: NDArray[np.int64]
    rows: NDArray[np.float32]
    neighbour_keys: NDArray[np.int64] | None


@dataclass(frozen=True, slots=True)
class _LevelAsk:
    """A tile's level to compute tile by tile: its voxels' positions (``queries``), where
    their rows go (``out``) and, for level 0, where their neighbours' keys go."""

    number: int
    queries: NDArray[np.float64]
    out: NDArray[np.float32]
    neighbour_keys: NDArray[np.int64] | None


@dataclass(frozen=True, slots=True)
class TileFeatures:
    """Feature rows of the selected points of one tile.

    Attributes:
        tile: ``(ix, iy)`` tile index.
        point_indices: ``(m,)`` int64 indices of the points in the whole scan, ascending.
        table: rows for those points (``table.point_row`` aligned with ``point_indices``).
        labels: ``(m,)`` uint8 label values when the chunks carried labels, else None.
        xyz: ``(m, 3)`` float64 absolute positions of those points (None when not asked
            for: :meth:`TiledScan.tile_features`).
    """

    tile: Tile
    point_indices: NDArray[np.int64]
    table: FeatureTable
    labels: NDArray[np.uint8] | None
    xyz: NDArray[np.float64] | None


def _gather_level_columns(
    sources: list[tuple[int, NDArray[np.float32], NDArray[np.int64] | None]],
    width: int,
    start: int,
    out: NDArray[np.float32],
) -> None:
    """Rows ``start .. start + len(out)`` of a tile's table into ``out``: level ``n``'s
    columns of a row are ``rows[index[row]]`` of its source ``(n, rows, index)`` (index
    None: the source's rows are the table's, in order)."""
    stop = start + out.shape[0]
    for number, rows, index in sources:
        columns = out[:, number * width : (number + 1) * width]
        if index is None:
            columns[:] = rows[start:stop]
        else:
            put_rows(rows, index[start:stop], columns, 0)  # columns[:] = rows[index[...]]


class TiledScan:
    """A scan spilled into tiles on disk, ready for tiled feature computation.

    Use as a context manager: the working files are removed on exit.

    Args:
        chunks: the scan as point chunks, in file order (e.g. ``iter_ascii_points``).
        config: feature settings (the tiles align to its coarsest voxel).
        tile_size_m: tile edge; rounded up to a multiple of the coarsest voxel size.
        workdir: folder in which a scratch folder for the tiles is made (default: the
            system's temporary folder); the scratch folder is removed on close.
        cache_bytes: memory kept for pyramid levels of recently used tiles (halos read
            the neighbours' levels again and again).
        whole_level_points: in voxel mode, the coarsest levels holding together at most
            this many voxels are described in one pass instead of tile by tile (same rows,
            no halo; ~80 bytes per voxel held until the scan is closed).
    """

    def __init__(
        self,
        chunks: Iterable[PointCloud],
        *,
        config: FeatureConfig,
        tile_size_m: float = DEFAULT_TILE_SIZE_M,
        workdir: str | Path | None = None,
        cache_bytes: int = 96 << 20,
        whole_level_points: int = 1_000_000,
    ) -> None:
        if not tile_size_m > 0:
            raise ConfigError(f"tile_size_m: expected a positive size, found {tile_size_m}")
        self.config = config
        cells_per_coarsest = 2 ** (config.n_levels - 1)
        self.tile_cells = cells_per_coarsest * max(
            1, math.ceil(tile_size_m / config.coarsest_voxel_size_m - 1e-9)
        )
        self.tile_size_m = self.tile_cells * config.base_voxel_size_m
        if workdir is not None:
            Path(workdir).mkdir(parents=True, exist_ok=True)
        self.workdir = Path(tempfile.mkdtemp(prefix="s3d-tiles-", dir=workdir))
        self.origin: NDArray[np.float64] = np.zeros(3)
        self._level_sizes = [0] * config.n_levels
        self._densest_sizes = [0] * config.n_levels  # the densest tile's level sizes
        self._first_halo: dict[int, float] = {}
        self._whole: dict[int, _WholeLevel | None] = {}
        self.whole_level_points = whole_level_points
        self.cache_bytes = cache_bytes
        self._cache: OrderedDict[tuple[Tile, int], _TileLevel | NDArray[np.int64]] = OrderedDict()
        self._cache_bytes = 0
        self._cache_scale = 1  # tiles computed at once: each keeps its neighbours cached
        self._part_starts: dict[Tile, tuple[int, ...]] = {}  # in a tile's pyramid file
        self._base_voxels: dict[Tile, int] = {}  # each tile's level-0 voxels
        # pyramids built and kept in memory, not written (the pyramid pass's last ones;
        # written when the scan is pickled)
        self._kept: dict[Tile, list[_TileLevel | NDArray[np.int64]]] = {}
        self._kept_bytes = 0
        self._lock = threading.Lock()
        self._writing = threading.Lock()  # one writer of the kept pyramids at a time
        try:
            self.store = self._spill(chunks)
            tiles = np.array(self.store.tiles)
            self._tile_low = tiles.min(axis=0) * self.tile_size_m - _SLACK_M
            self._tile_high = (tiles.max(axis=0) + 1) * self.tile_size_m + _SLACK_M
            self._build_pyramids()
        except BaseException:
            self.close()
            raise

    # -- resource protocol ---------------------------------------------------------------
    def __enter__(self) -> TiledScan:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.close()

    def close(self) -> None:
        """Remove the scratch folder and everything in it."""
        self._cache.clear()
        self._kept.clear()
        self._kept_bytes = 0
        shutil.rmtree(self.workdir, ignore_errors=True)

    @property
    def tiles(self) -> tuple[Tile, ...]:
        """Non-empty tiles, sorted."""
        return self.store.tiles

    @property
    def n_points(self) -> int:
        """Points in the scan."""
        return self.store.n_points

    @property
    def has_labels(self) -> bool:
        """Whether the chunks carried labels."""
        return self.store.has_labels

    # -- pass 1: spill ---------------------------------------------------------------------
    def _spill(self, chunks: Iterable[PointCloud]) -> TileStore:
        """Stream the chunks into a tile store whose tiles are whole coarsest voxels."""
        stream = iter(chunks)
        first = next((chunk for chunk in stream if chunk.n_points), None)
        if first is None:
            raise ShapeError("cannot tile an empty scan")
        config = self.config
        self.origin = grid_origin(first.xyz[0], coarsest_voxel_size_m=config.coarsest_voxel_size_m)
        grid = TileGrid(
            origin_xy=(float(self.origin[0]), float(self.origin[1])),
            cell_size_m=config.base_voxel_size_m,
            cells_per_tile=self.tile_cells,
        )
        # the next chunks are read (parsed on their own thread) while these are binned,
        # the first among them; binning (compiled counting sorts) costs about half as much
        # as parsing: a third of the threads bin, the rest parse
        ahead = iter_ahead(
            chain([first], stream), consumer_threads=max(1, thread_budget() // 3), name="s3d-spill"
        )
        with span("spill") as attrs:
            store = build_tile_store(ahead, self.workdir / "points", grid=grid)
            attrs.update(points=store.n_points, tiles=len(store.tiles))
        logger.info("spilled %d points into %d tiles", store.n_points, len(store.tiles))
        return store

    def _load_points(self, tile: Tile) -> TilePoints:
        return self.store.read_core(tile)

    def _attributes(self, points: TilePoints) -> NDArray[np.float64] | None:
        return attribute_columns(points.cloud, self.config)

    # -- pass 2: pyramids ------------------------------------------------------------------
    def _pyramid_path(self, tile: Tile) -> Path:
        return self.workdir / f"{tile[0]}_{tile[1]}.pyramid.pickle"

    def _build_pyramids(self) -> None:
        """Every tile's pyramid, written to the scratch folder: tiles at the same time on
        the thread budget's threads, the largest first (the last to end is then a small
        one), each tile's kernels on a share of the threads in proportion to its points
        (the densest tile, near the scanner, holds over half of them); the level sizes are
        summed."""
        n_threads = thread_budget()
        total = max(1, self.n_points)
        order = sorted(self.tiles, key=lambda tile: (-self.store.count(tile), tile))
        for rank, (tile, sizes) in enumerate(
            zip(
                order,
                map_in_threads(
                    lambda tile: self._build_pyramid(tile, n_threads),
                    order,
                    n_threads=n_threads,
                    numba_threads_per_task=lambda tile: math.ceil(
                        n_threads * self.store.count(tile) / total
                    ),
                    name="s3d-pyramid",
                ),
                strict=True,
            )
        ):
            if rank == 0:  # the densest tile (the first halos are estimated in it)
                self._densest_sizes = list(sizes)
            self._base_voxels[tile] = sizes[0]
            for number, n_voxels in enumerate(sizes):
                self._level_sizes[number] += n_voxels

    def _build_pyramid(self, tile: Tile, n_threads: int = 1) -> list[int]:
        """Build a tile's pyramid and write it (or keep it in memory, within bounds, when
        the pass runs on ``n_threads`` > 1); return its level sizes."""
        with span("pyramid", tile=[int(v) for v in tile], points=int(self.store.count(tile))):
            return self._build_pyramid_of(tile, n_threads)

    def _build_pyramid_of(self, tile: Tile, n_threads: int) -> list[int]:
        config = self.config
        n_points = self.store.count(tile)
        if n_points > PYRAMID_PART_POINTS:  # a part's points at a time
            n_attributes = 3 * config.colour + config.intensity
            pyramid = build_pyramid_in_parts(
                (  # contiguous coordinates, copied on every thread
                    (part.copied().cloud.xyz, self._attributes(part))
                    for part in self.store.iter_core_parts(tile, PYRAMID_PART_POINTS)
                ),
                n_points=n_points,
                base_voxel_size_m=config.base_voxel_size_m,
                n_levels=config.n_levels,
                origin=self.origin,
                n_attributes=n_attributes,
            )
        else:
            points = self._load_points(tile).copied()  # contiguous, copied on every thread
            pyramid = build_pyramid(
                points.cloud.xyz,
                base_voxel_size_m=config.base_voxel_size_m,
                n_levels=config.n_levels,
                origin=self.origin,
                attributes=self._attributes(points),
            )
            del points
        # level by level, one after another in the tile's file: a level described whole,
        # or a halo, reads its level alone
        parts: list[_TileLevel | NDArray[np.int64]] = [
            _TileLevel(level.xyz, level.keys, level.attributes, level.parent)
            for level in pyramid.levels
        ]
        parts.append(pyramid.point_voxel)
        # The pass's last pyramids (the densest tiles: they start first and end last) are
        # kept in memory, not written (on one thread, while the others waited for the
        # pass's end) nor read back: memory stays bounded, at most a thread count of the
        # cache's bytes is kept (the tiles' pass caches as much). Written when the scan
        # is pickled for another process.
        size = sum(part.nbytes for part in parts)
        with self._lock:
            keep = n_threads > 1 and self._kept_bytes + size <= self.cache_bytes * n_threads
            if keep:
                self._kept[tile] = parts
                self._kept_bytes += size
        if not keep:
            # on one thread: the task's other threads go back to the map meanwhile
            with serial_section():
                self._write_pyramid(tile, parts)
        return [level.n_voxels for level in pyramid.levels]

    def _write_pyramid(self, tile: Tile, parts: list[_TileLevel | NDArray[np.int64]]) -> None:
        """Write a tile's pyramid parts one after another in its scratch file (a level
        described whole, or a halo, reads its level alone)."""
        starts = []
        with self._pyramid_path(tile).open("wb") as stream:
            for value in parts:
                starts.append(stream.tell())
                pickle.dump(value, stream, protocol=pickle.HIGHEST_PROTOCOL)
        with self._lock:  # readers find the parts in one place or the other
            self._part_starts[tile] = tuple(starts)
            if self._kept.pop(tile, None) is not None:
                self._kept_bytes -= sum(part.nbytes for part in parts)

    def _write_kept(self) -> None:
        """Write the pyramids still kept in memory (one after another, on this thread;
        a second caller, e.g. another thread pickling the scan, waits for the first)."""
        with self._writing:
            for tile, parts in list(self._kept.items()):
                self._write_pyramid(tile, parts)

    def _level(self, tile: Tile, number: int) -> _TileLevel:
        """Level ``number`` of a tile's pyramid (through the cache)."""
        level = self._pyramid_part(tile, number)
        assert isinstance(level, _TileLevel)
        return level

    def _point_voxels(self, tile: Tile) -> NDArray[np.int64]:
        """The level-0 voxel of each of a tile's points (through the cache)."""
        point_voxel = self._pyramid_part(tile, -1)
        assert isinstance(point_voxel, np.ndarray)
        return point_voxel

    def _pyramid_part(self, tile: Tile, part: int) -> _TileLevel | NDArray[np.int64]:
        """A tile's pyramid part (level ``part``, or ``-1``: the level-0 voxel of each of
        its points) through a byte-bounded LRU cache of parts (halos and the
        levels described whole reread them; a part is one level, so a level gathered over
        every tile does not push the tiles' other levels through the cache)."""
        key = (tile, part)
        with self._lock:
            cached = self._cache.get(key)
            if cached is not None:
                self._cache.move_to_end(key)
                return cached
            kept = self._kept.get(tile)
            if kept is not None:
                return kept[part]
        # A scratch file this object wrote itself: pickle loads it ~5x faster than npz.
        with self._pyramid_path(tile).open("rb") as stream:
            stream.seek(self._part_starts[tile][part])
            value: _TileLevel | NDArray[np.int64] = pickle.load(stream)
        with self._lock:  # another thread may have loaded it meanwhile: keep one copy
            cached = self._cache.get(key)
            if cached is not None:
                return cached
            self._cache[key] = value
            self._cache_bytes += value.nbytes
            limit = self.cache_bytes * self._cache_scale
            while self._cache_bytes > limit and len(self._cache) > 1:
                _, evicted = self._cache.popitem(last=False)
                self._cache_bytes -= evicted.nbytes
        return value

    # -- pass 3: features ------------------------------------------------------------------
    def iter_features(
        self,
        *,
        select: ArrayLike | None = None,
        row_map: RowMap | None = None,
        positions: bool = True,
    ) -> Iterator[TileFeatures]:
        """Feature rows tile by tile (tiles in sorted order, points ascending inside).

        Args:
            select: global indices of the points to describe (default all); tiles without
                a selected point are skipped.
            row_map: map each tile's rows as they are made (:meth:`tile_features`).
            positions: give the points' positions (:meth:`tile_features`).
        """
        wanted = None if select is None else np.unique(np.asarray(select, dtype=np.int64))
        for tile in self.tiles:
            features = self.tile_features(tile, select=wanted, row_map=row_map, positions=positions)
            if features is not None:
                yield features

    def tile_features(
        self,
        tile: Tile,
        *,
        select: NDArray[np.int64] | None = None,
        row_map: RowMap | None = None,
        positions: bool = True,
    ) -> TileFeatures | None:
        """Feature rows of one tile (its points ascending), None when none is selected.

        The unit of work of :meth:`iter_features`, which other processes can do as well:
        a ``TiledScan`` pickles to its scratch folder's path and a few numbers (no cache),
        and a copy opened where that folder is visible gives the same rows.

        Args:
            tile: one of :attr:`tiles`.
            select: sorted unique global indices of the points to describe (default all).
            row_map: map the rows :data:`~semantic3d.features.multiscale.ROW_BLOCK` at a
                time as they are made, each level's distinct rows held instead of the
                table (a million-row tile's table is 600 MB at the default 153 columns):
                the table's :attr:`~semantic3d.features.multiscale.FeatureTable.mapped`
                holds the results, its ``values`` no columns.
            positions: give the points' positions (:attr:`TileFeatures.xyz`; else None,
                and a tile of voxel rows copies only its points' indices and labels).
        """
        points = self._load_points(tile)
        xyz: NDArray[np.float64] | None
        if select is None:  # every point: one copy of the columns, on every thread
            if points.n_points == 0:
                return None
            # a tile of voxel rows needs no positions of its points
            copied = positions or self.config.per_point
            points = points.copied(positions=copied)
            labels, indices, local = points.cloud.labels, points.indices, None
            xyz = points.cloud.xyz if copied else None
        else:
            keep = np.isin(points.indices, select, assume_unique=True)
            if not keep.any():
                return None
            labels = points.cloud.labels[keep] if points.cloud.labels is not None else None
            xyz, indices, local = points.cloud.xyz[keep], points.indices[keep], np.flatnonzero(keep)
        # the store's pages of the tile (44 bytes a point) are let go of before the rows
        # are made, which takes the tile's longest
        del points
        table = self._tile_table(tile, xyz, local, row_map)
        return TileFeatures(tile, indices, table, labels, xyz if positions else None)

    def share(self) -> None:
        """Compute what every tile shares once and save it in the scratch folder.

        The coarse levels described whole and each level's first halo are written to the
        scratch folder; copies of this scan unpickled in other processes read them there
        instead of computing them again (the same values: the same rows).
        """
        self._compute_shared()
        partial = self.workdir / f".{_SHARED_FILE}.partial"
        with partial.open("wb") as stream:
            pickle.dump((self._whole, self._first_halo), stream, protocol=pickle.HIGHEST_PROTOCOL)
        partial.replace(self.workdir / _SHARED_FILE)

    def _compute_shared(self) -> None:
        """The coarse levels described whole and every level's first halo (what every
        tile reads; computed before tiles are computed at the same time).

        Levels are independent: they are computed at the same time on the thread budget's
        threads, the largest first, numba's kernels of each on a share of the threads in
        proportion to its work: the level's voxels when it is described whole (at
        :data:`_WHOLE_VOXEL_COST` each) and the densest tile's level voxels its first
        halo's tree is built over (level 0's first halo, the largest tree, had one thread
        while the small levels had the others; then the largest level described whole
        had one thread while level 0's ran).
        """
        config = self.config
        numbers = [n for n in range(config.n_levels) if n not in self._first_halo]
        if not numbers:
            return
        n_threads = thread_budget()
        weight = {
            n: self._densest_sizes[n]
            + (
                _WHOLE_VOXEL_COST * self._level_sizes[n]
                if not config.per_point and self._described_whole(n)
                else 0
            )
            for n in numbers
        }
        total = max(1, sum(weight.values()))

        def compute(number: int) -> None:
            if not config.per_point:
                take_free_threads()  # the last levels go on with the threads others left
                with span("whole level", level=number):
                    self._whole_level(number)
            take_free_threads()
            with span("first halo", level=number):
                self._first_halo_m(number)

        for _ in map_in_threads(
            compute,
            sorted(numbers, key=lambda n: (-weight[n], n)),
            n_threads=n_threads,
            ordered=False,
            numba_threads_per_task=lambda n: max(1, math.ceil(n_threads * weight[n] / total)),
            name="s3d-shared",
        ):
            pass

    def map_tiles(
        self,
        function: Callable[[TileFeatures], R],
        *,
        select: ArrayLike | None = None,
        n_threads: int | None = None,
        row_map: RowMap | None = None,
        positions: bool = True,
    ) -> Iterator[R]:
        """``function(features)`` for every tile with a selected point, tiles at the same time.

        Each tile's rows are those of :meth:`tile_features` (so those of
        :meth:`iter_features`), and ``function`` runs on the thread that computed them:
        tiles are described and used on ``n_threads`` threads (default the thread budget,
        :mod:`semantic3d.core.threads`), the most work first, results as they finish (at
        most twice ``n_threads`` held at once). Inside a tile, numba's kernels get a share
        of the threads in proportion to the tile's work (:meth:`_work`: its voxels more
        than its points; :func:`~semantic3d.core.threads.apportion_threads`), so a scan
        whose points crowd into a few tiles near the scanner still uses every core, and
        the tiles around them, with fewer points in more voxels, are not left on too few
        threads to the end. Tiles of less than a thread's share run one thread each,
        beside the large tiles on the threads their work earns together, not all after
        them. With ``row_map`` each tile's rows are mapped as they are made
        (:meth:`tile_features`), on the tile's threads; ``positions``: as there.
        """
        wanted = None if select is None else np.unique(np.asarray(select, dtype=np.int64))
        n_threads = thread_budget() if n_threads is None else max(1, int(n_threads))
        self._compute_shared()
        work = {tile: self._work(tile) for tile in self.tiles}
        order = sorted(self.tiles, key=lambda tile: (-work[tile], tile))
        shares = apportion_threads(work, n_threads)

        def threads_of(tile: Tile) -> int:
            return shares[tile]

        def task(tile: Tile) -> tuple[bool, R | None]:
            with span(
                "tile",
                tile=[int(v) for v in tile],
                points=int(self.store.count(tile)),
                threads=threads_of(tile),
            ):
                with span("features", threads=thread_budget()):
                    features = self.tile_features(
                        tile, select=wanted, row_map=row_map, positions=positions
                    )
                return (False, None) if features is None else (True, function(features))

        self._cache_scale = n_threads
        try:
            for found, result in map_in_threads(
                task,
                order,
                n_threads=n_threads,
                ordered=False,
                numba_threads_per_task=threads_of,
                name="s3d-tile",
            ):
                if found:
                    yield result  # type: ignore[misc]
        finally:
            self._cache_scale = 1

    def _work(self, tile: Tile) -> float:
        """A tile's share of the feature pass and what follows it, for sharing threads out
        (:data:`_POINT_WORK_VOXELS`); per-point rows: its points, each a query at every
        level."""
        points = self.store.count(tile)
        if self.config.per_point:
            return float(points)
        return self._base_voxels[tile] + _POINT_WORK_VOXELS * points

    def __getstate__(self) -> dict[str, object]:
        """What travels to another process: paths and numbers, no cached pyramid or rows
        (the pyramids kept in memory are written first)."""
        self._write_kept()
        state = dict(self.__dict__)
        state["_cache"] = OrderedDict()
        state["_cache_bytes"] = 0
        state["_whole"] = {}
        del state["_lock"], state["_writing"]
        return state

    def __setstate__(self, state: dict[str, object]) -> None:
        self.__dict__.update(state)
        self._lock = threading.Lock()
        self._writing = threading.Lock()
        shared = self.workdir / _SHARED_FILE
        if shared.is_file():  # written by share() in the process that made the scan
            with shared.open("rb") as stream:
                self._whole, self._first_halo = pickle.load(stream)

    def _tile_table(
        self,
        tile: Tile,
        xyz: NDArray[np.float64] | None,
        local: NDArray[np.int64] | None,
        row_map: RowMap | None = None,
    ) -> FeatureTable:
        """Rows of the tile's points ``local`` (its points' positions in the tile; None:
        every point), at ``xyz``; with ``row_map``, the rows mapped block by block
        (:meth:`tile_features`)."""
        assert self.origin is not None
        config = self.config
        width = len(config.level_feature_names)
        if config.per_point:
            assert xyz is not None
            queries = xyz - self.origin
            values = np.empty((queries.shape[0], config.n_features), np.float32)
            for number in range(config.n_levels):
                values[:, number * width : (number + 1) * width] = self._exact_level(
                    tile, number, queries
                )
            table = FeatureTable(
                config.feature_names, values, np.arange(queries.shape[0], dtype=np.int64)
            )
            return table if row_map is None else map_table_rows(table, row_map)
        levels = [self._level(tile, number) for number in range(config.n_levels)]  # held
        point_voxels = self._point_voxels(tile)
        if local is None:  # every level-0 voxel holds points of the tile: rows are voxels
            voxels = np.arange(levels[0].n_voxels, dtype=np.int64)
            point_row = point_voxels.view()  # not a copy of 8 bytes a point
            point_row.flags.writeable = False
        else:
            voxels, point_row = distinct_voxels(point_voxels[local])
        # the table whole, or (with row_map) only each level's distinct rows: a row's
        # columns of level n are ``rows[index[row]]`` of its source (index None: in order)
        table_values = (
            np.empty((voxels.size, config.n_features), np.float32) if row_map is None else None
        )
        sources: list[tuple[int, NDArray[np.float32], NDArray[np.int64] | None]] = []
        # level 0 (one row per voxel, in row order) also gives every row its k-NN
        neighbour_keys = np.empty((voxels.size, config.k_neighbours), np.int64)
        take_free_threads()  # a map's last tiles go on with the threads others left
        asks: list[_LevelAsk] = []
        ancestor = voxels
        for number in range(config.n_levels):
            if number:
                ancestor = levels[number - 1].parent[ancestor]
            needed, inverse = level_rows(ancestor)
            whole = self._whole_level(number)
            if whole is not None:  # looked up in the rows of the level described whole
                at = np.searchsorted(whole.keys, levels[number].keys[needed])
                if number == 0 and whole.neighbour_keys is not None:  # rows are its voxels
                    found = whole.neighbour_keys.shape[1]
                    put_rows(whole.neighbour_keys, at, neighbour_keys[:, :found], 0)
                    neighbour_keys[:, found:] = -1
                sources.append((number, whole.rows, at if inverse is None else at[inverse]))
                continue
            level = levels[number]
            if inverse is None and table_values is not None:  # computed in place
                out = table_values[:, number * width : (number + 1) * width]
            else:
                out = np.empty((needed.size, width), np.float32)
                sources.append((number, out, inverse))
            queries = level.xyz if needed.size == level.n_voxels else take_rows(level.xyz, needed)
            asks.append(_LevelAsk(number, queries, out, neighbour_keys if number == 0 else None))
        with span("levels", levels=[a.number for a in asks], threads=thread_budget()) as attrs:
            attrs["parts"] = self._exact_levels_in_parts(tile, asks)
            attrs["threads_after"] = thread_budget()
        neighbours = rows_of_keys(neighbour_keys, levels[0].keys[voxels], in_place=True)
        del neighbour_keys  # now the neighbours' rows
        # a scan of fewer than k level-0 voxels has fewer neighbours: as the whole-scan path
        width_found = min(config.k_neighbours, self._level_sizes[0])
        neighbours = neighbours[:, :width_found]
        if table_values is not None:
            _gather_level_columns(sources, width, 0, table_values)
            return FeatureTable(config.feature_names, table_values, point_row, neighbours)
        assert row_map is not None

        def fill(start: int, out: NDArray[np.float32]) -> None:
            _gather_level_columns(sources, width, start, out)

        return FeatureTable(
            config.feature_names,
            np.empty((voxels.size, 0), np.float32),
            point_row,
            neighbours,
            mapped=map_rows(voxels.size, config.n_features, fill, row_map),
        )

    def _whole_level(self, number: int) -> _WholeLevel | None:
        """Features of every voxel of a small level, computed once over the whole level.

        Coarse levels hold few voxels; describing them in one pass needs no halo and saves
        a k-NN call per tile. Levels are taken from the coarsest down while their voxels
        add up to at most ``whole_level_points``, so the rows kept stay bounded. Returns
        the level's sorted keys and rows (and, for level 0, its neighbours' keys), or None
        for the levels that go tile by tile.
        """
        if number in self._whole:
            return self._whole[number]
        result = None
        if self._described_whole(number):
            box = np.array([-np.inf, np.inf, -np.inf, np.inf])
            xyz, keys, attributes = self._gather(number, box)
            order = np.argsort(keys)
            xyz, keys, attributes = xyz[order], keys[order], attributes[order]
            neighbour_keys = (
                np.empty((keys.size, min(self.config.k_neighbours, keys.size)), np.int64)
                if number == 0
                else None
            )
            rows, _ = compute_level_features(
                LevelIndex(xyz, keys),
                attributes,
                xyz,
                config=self.config,
                level=number,
                neighbours=neighbour_keys,
            )
            if neighbour_keys is not None:
                neighbour_keys = keys[neighbour_keys]
            result = _WholeLevel(keys, rows, neighbour_keys)
        self._whole[number] = result
        return result

    def _described_whole(self, number: int) -> bool:
        """Whether level ``number`` is described whole (see :meth:`_whole_level`)."""
        return sum(self._level_sizes[number:]) <= self.whole_level_points

    def _first_halo_m(self, number: int) -> float:
        """The halo a level's queries start with: most of them need no second ask.

        Estimated once per level from a sample of the densest tile's level points (the
        95th percentile of their k-th neighbour distance), never from the tiles visited
        before, so a tile's work does not depend on the order tiles are computed in. Any
        value gives the same rows; a good one saves re-queries.
        """
        cached = self._first_halo.get(number)
        if cached is not None:
            return cached
        config = self.config
        floor = _FIRST_HALO_VOXELS * config.voxel_sizes_m[number]
        densest = max(self.tiles, key=self.store.count)
        level = self._level(densest, number)
        halo = floor
        if level.n_voxels >= config.k_neighbours:
            step = max(1, level.n_voxels // _HALO_SAMPLE)
            sample = level.xyz[::step]
            # the reach the features would give the sample, without the features
            reach = level_reach(
                LevelIndex(level.xyz, level.keys), sample, config=config, level=number
            )
            halo = max(floor, 1.1 * float(np.quantile(reach, 0.95)))
        self._first_halo[number] = halo
        return halo

    def _exact_levels_in_parts(self, tile: Tile, asks: list[_LevelAsk]) -> int:
        """:meth:`_exact_level` of a tile's levels' queries (``asks``), in parts computed
        at the same time, every level's in one map: the threads a level's last parts leave
        go to the other levels' parts, not to other tiles (which kept them) while the next
        level waits. A level is cut into parts when the tile's task has several threads or
        may get them (one thread of a large map: the map of parts grows as other tiles
        end, :func:`map_in_threads`): blocks of a grid across the tile
        (strips of consecutive queries in key order, i.e. along x, each cut along y), of
        about equal work (:func:`part_blocks`), each part on one thread from its own box
        (its extent plus the first halo), so what one part runs alone another overlaps.
        Every row is exact whatever box it starts from: the same rows as in one piece.
        The largest parts start first; the tile keeps its threads through the parts'
        tail (short, the parts being many) for its next steps. Returns the number of parts.

        Blocks, not strips: a box's halo is a smaller share of a square than of a thin
        strip, which more threads make thinner; and the queries a part asks again lie
        along its edges, which for a strip cross the whole tile."""
        n_threads = thread_budget()
        if n_threads > 1:
            planned = _PARTS_PER_THREAD * n_threads
        else:  # on one thread: parts only where other tiles' threads may join them
            planned = _GROWING_PARTS if enclosing_map_threads() >= _GROWING_MAP_THREADS else 1
        pieces: list[tuple[float, _LevelAsk, tuple[int, int, float, float] | None]] = []
        for ask in asks:
            n = ask.queries.shape[0]
            n_parts = min(planned, n // _MIN_PART_QUERIES)
            if n_parts <= 1:
                pieces.append((n, ask, None))
                continue
            blocks = part_blocks(
                ask.queries, n_parts, _COST_CELL_RADII * self.config.cylinder_radius_m(ask.number)
            )
            pieces.extend((n / len(blocks), ask, block) for block in blocks)
        if len(pieces) == 1:  # one level in one piece: its kernels on every thread
            _, ask, _ = pieces[0]
            self._exact_level(tile, ask.number, ask.queries, ask.neighbour_keys, out=ask.out)
            return 1
        pieces.sort(key=lambda piece: -piece[0])  # stable: a level's blocks stay in order

        def compute(piece: tuple[float, _LevelAsk, tuple[int, int, float, float] | None]) -> None:
            _, ask, block = piece
            queries, out, neighbour_keys = ask.queries, ask.out, ask.neighbour_keys
            if block is None:
                self._exact_level(tile, ask.number, queries, neighbour_keys, out=out)
                return
            start, stop, y_low, y_high = block
            strip_y = queries[start:stop, 1]
            rows = start + np.flatnonzero((strip_y >= y_low) & (strip_y < y_high))
            if rows.size == 0:
                return
            asked = take_rows(queries, rows)
            found = (
                None
                if neighbour_keys is None
                else np.empty((rows.size, neighbour_keys.shape[1]), np.int64)
            )
            values = np.empty((rows.size, out.shape[1]), np.float32)
            self._exact_level(
                tile,
                ask.number,
                asked,
                found,
                out=values,
                around=np.array(
                    [asked[:, 0].min(), asked[:, 0].max(), asked[:, 1].min(), asked[:, 1].max()]
                ),
            )
            scatter_rows(values, rows, out)
            if neighbour_keys is not None and found is not None:
                scatter_rows(found, rows, neighbour_keys)

        # no loan of the parts' tail to other tiles: the tail is short (many parts), and
        # threads lent to start a tile come back only when it ends, long after this
        # tile's forest and cut began on the few left (seen on 16 cores)
        for _ in map_in_threads(
            compute, pieces, n_threads=n_threads, ordered=False, lend_tail=False, name="s3d-part"
        ):
            pass
        return len(pieces)

    def _exact_level(
        self,
        tile: Tile,
        number: int,
        queries: NDArray[np.float64],
        neighbour_keys: NDArray[np.int64] | None = None,
        *,
        out: NDArray[np.float32] | None = None,
        around: NDArray[np.float64] | None = None,
    ) -> NDArray[np.float32]:
        """Level ``number`` features of ``queries`` (in ``tile``), widening the halo until exact.

        First the tile (or ``around``: ``x_low, x_high, y_low, y_high`` holding the
        queries) plus the level's first halo (:meth:`_first_halo_m`); a query whose k-th
        neighbour lies beyond the halo's edge is asked again in a box containing the ball
        of that radius (the k-th distance within a subset bounds the true one), which is
        then exact; a subset with fewer than k points doubles the box. The queries left
        by the first ask are asked again piece by piece: those nearest each piece of each
        side of its box in a box of their own (a thin band along that piece, not the
        first box again). With
        ``neighbour_keys`` (``(m, k)``), also the keys of every query's exact neighbours.
        The rows go to ``out`` (``(m, n_level_features)``, may be a column slice) when given.
        """
        config = self.config
        size = self.tile_size_m
        if out is None:
            out = np.empty((queries.shape[0], len(config.level_feature_names)), np.float32)
        halo = self._first_halo_m(number)
        if around is None:
            around = np.array(
                [tile[0] * size, (tile[0] + 1) * size, tile[1] * size, (tile[1] + 1) * size]
            )
        # (queries asked, box): None, the first ask, is every query
        asks: list[tuple[NDArray[np.intp] | None, NDArray[np.float64]]] = [
            (None, np.asarray(around, dtype=np.float64) + np.array([-halo, halo, -halo, halo]))
        ]
        while asks:
            pending, box = asks.pop()
            box[[0, 2]] = np.maximum(box[[0, 2]], self._tile_low - 1.0)
            box[[1, 3]] = np.minimum(box[[1, 3]], self._tile_high + 1.0)
            infinite = np.array(
                [
                    box[0] <= self._tile_low[0],
                    box[1] >= self._tile_high[0],
                    box[2] <= self._tile_low[1],
                    box[3] >= self._tile_high[1],
                ]
            )
            xyz, keys, attributes = self._gather(number, box)
            asked = queries if pending is None else queries[pending]
            found = (
                np.empty((asked.shape[0], min(config.k_neighbours, keys.size)), np.int64)
                if neighbour_keys is not None
                else None
            )
            # the first ask writes every row in place; rows it cannot vouch for are
            # written again by a later ask
            block, kth = compute_level_features(
                LevelIndex(xyz, keys),
                attributes,
                asked,
                config=config,
                level=number,
                neighbours=found,
                out=out if pending is None else None,
            )
            enough = xyz.shape[0] >= config.k_neighbours
            if infinite.all():
                exact = np.ones(asked.shape[0], bool)
            else:
                exact = exact_rows(asked, kth, box, infinite, enough, _SAFETY_M)
            if pending is None:
                if neighbour_keys is not None and found is not None:
                    store_keys(keys, found, exact, neighbour_keys)
                left = np.flatnonzero(~exact)
            else:
                out[pending[exact]] = block[exact]
                if neighbour_keys is not None and found is not None:
                    rows = pending[exact]
                    neighbour_keys[rows] = -1
                    neighbour_keys[rows, : found.shape[1]] = keys[found[exact]]
                left = pending[~exact]
            if left.size:
                if enough:
                    radius = kth[~exact] * (1.0 + 1e-6) + 2.0 * _SAFETY_M
                else:
                    radius = self._reach_bound(number, queries[left], box)
                # after the first ask, a box a piece of each side of it: the queries left
                # lie along its edges, and one box around them all held it all again
                sides = (
                    _nearest_sides(queries[left], box)
                    if pending is None
                    else np.zeros(left.size, np.int64)
                )
                for side in np.unique(sides).tolist():
                    chosen = sides == side
                    asks.append((left[chosen], _ball_box(queries[left[chosen]], radius[chosen])))
        return out

    def _reach_bound(
        self, number: int, queries: NDArray[np.float64], box: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        """A reach at least each query's, with the halo test's margins, for queries whose
        ``box`` held fewer than k level points (a sparse tile's few voxels).

        The k-th distance among the points of the box grown about itself (doubled, again
        while it holds fewer than k) bounds the true k-th distance, so the ball box of the
        bound holds every neighbour and the next ask is exact. Only distances are computed
        in the grown box: describing the queries there, as a box grown by its width and
        height was, built a tree and cylinders over the dense tiles around for a handful
        of rows. A level of fewer than k points gets the box's width plus height (the
        boxes then grow until they hold the whole level)."""
        config = self.config
        k = config.k_neighbours
        if self._level_sizes[number] < k:  # no box ever holds k
            return np.full(queries.shape[0], box[1] - box[0] + box[3] - box[2])
        wide = np.array(box, dtype=np.float64)
        while True:  # ends: a box over every tile holds the whole level
            grow = 0.5 * max(wide[1] - wide[0], wide[3] - wide[2])
            wide += np.array([-grow, grow, -grow, grow])
            xyz, keys, _ = self._gather(number, wide)
            if xyz.shape[0] >= k:
                break
        if queries.shape[0] * xyz.shape[0] <= _BRUTE_FORCE_PAIRS:
            kth = np.sqrt(kth_squared_distances(xyz, queries, k))
        else:  # many queries (per-point rows): a tree over the grown box
            kth = LevelIndex(xyz, keys).query(queries, k=k).kth_distance
        bound: NDArray[np.float64] = (
            reach_of_kth(kth, config, number) * (1.0 + 1e-6) + 2.0 * _SAFETY_M
        )
        return bound

    def _gather(
        self, number: int, box: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.int64], NDArray[np.float64]]:
        """Level ``number`` points of every tile that lie inside ``box``."""
        size = self.tile_size_m
        voxel = self.config.voxel_sizes_m[number]
        low = np.maximum(box[[0, 2]], self._tile_low)
        high = np.minimum(box[[1, 3]], self._tile_high)
        x_low, x_high = (
            math.floor((low[0] - _SLACK_M) / size),
            math.floor((high[0] + _SLACK_M) / size),
        )
        y_low, y_high = (
            math.floor((low[1] - _SLACK_M) / size),
            math.floor((high[1] + _SLACK_M) / size),
        )
        if (x_high - x_low + 1) * (y_high - y_low + 1) <= len(self.tiles):
            candidates: Iterable[Tile] = (
                (ix, iy) for ix in range(x_low, x_high + 1) for iy in range(y_low, y_high + 1)
            )
        else:
            candidates = self.tiles
        parts: list[tuple[_TileLevel, NDArray[np.intp]]] = []
        for other in candidates:
            if other not in self.store or not (
                x_low <= other[0] <= x_high and y_low <= other[1] <= y_high
            ):
                continue
            level = self._level(other, number)
            first, last = _rows_across(level.keys, box[0], box[1], voxel)
            parts.append((level, first + rows_in_box(level.xyz[first:last], box)))
        # the parts' rows concatenated, copied on every thread
        total = sum(rows.size for _, rows in parts)
        xyz = np.empty((total, 3), np.float64)
        keys = np.empty(total, np.int64)
        attributes = np.empty((total, parts[0][0].attributes.shape[1]), np.float64)
        offset = 0
        for level, rows in parts:
            put_rows(level.xyz, rows, xyz, offset)
            put_values(level.keys, rows, keys, offset)
            put_rows(level.attributes, rows, attributes, offset)
            offset += rows.size
        return xyz, keys, attributes


def _sampled_work(
    queries: NDArray[np.float64], cell_m: float
) -> tuple[int, NDArray[np.float64], NDArray[np.float64]]:
    """Every ``step``-th query's ``x, y`` and estimated work: its k-NN search plus its
    cylinder's points, which grow with the level's points around it, as
    :data:`_QUERY_COST_POINTS` plus the sampled queries in its square of ``cell_m`` (the
    queries of a tile's level are its voxels), at most :data:`_BOUND_SAMPLE` of them."""
    n = queries.shape[0]
    step = max(1, -(-n // _BOUND_SAMPLE))
    sample = queries[::step, :2]
    cells = np.floor((sample - sample.min(axis=0)) / cell_m).astype(np.int64)
    codes = cells[:, 0] * (int(cells[:, 1].max()) + 1) + cells[:, 1]
    _, inverse, counts = np.unique(codes, return_inverse=True, return_counts=True)
    return step, sample, _QUERY_COST_POINTS + step * counts[inverse].astype(np.float64)


def _equal_work_bounds(
    n: int, n_parts: int, step: int, work: NDArray[np.float64]
) -> NDArray[np.int64]:
    """Bounds of ``n_parts`` runs of the ``n`` queries whose sampled work is ``work``."""
    total = np.cumsum(work)
    at = np.searchsorted(total, total[-1] * np.arange(1, n_parts) / n_parts)
    bounds = np.empty(n_parts + 1, np.int64)
    bounds[0], bounds[-1] = 0, n
    bounds[1:-1] = np.minimum(at * step, n)
    return np.maximum.accumulate(bounds)


def part_blocks(
    queries: NDArray[np.float64], n_parts: int, cell_m: float
) -> list[tuple[int, int, float, float]]:
    """About ``n_parts`` blocks of ``queries`` (sorted along x: a tile's level in key
    order) of about equal work, as ``(start, stop, y_low, y_high)``: the queries of rows
    ``start:stop`` whose y lies in ``[y_low, y_high)``. Strips of consecutive queries
    along x, each cut along y, at equal estimated work (:func:`_sampled_work`: equal
    counts of queries left the parts near the scanner half as long again as the others);
    as many strips as cuts a strip, so the blocks are about square. Every query lies in
    exactly one block; any blocks give the same rows."""
    n = queries.shape[0]
    across = max(1, round(math.sqrt(max(1, n_parts))))
    n_strips = -(-max(1, n_parts) // across)
    if n == 0 or not cell_m > 0:
        return [(0, n, -np.inf, np.inf)] if n else []
    step, sample, work = _sampled_work(queries, cell_m)
    strips = _equal_work_bounds(n, n_strips, step, work) if n_strips > 1 else np.array([0, n])
    blocks = []
    for a, b in pairwise(strips.tolist()):
        if b <= a:
            continue
        inside = slice(-(-a // step), -(-b // step))  # the sampled queries of rows a:b
        y, weight = sample[inside, 1], work[inside]
        cuts = [-np.inf]
        if y.size and across > 1:
            order = np.argsort(y, kind="stable")
            total = np.cumsum(weight[order])
            at = np.searchsorted(total, total[-1] * np.arange(1, across) / across)
            cuts += np.unique(y[order][np.minimum(at, y.size - 1)]).tolist()
        cuts.append(np.inf)
        blocks += [(a, b, low, high) for low, high in pairwise(cuts)]
    return blocks


def _rows_across(
    keys: NDArray[np.int64], x_low: float, x_high: float, voxel_m: float
) -> tuple[int, int]:
    """The run of a level's rows (sorted by key: by voxel column along x first) that holds
    every voxel whose centre may lie in ``[x_low, x_high]`` (one column of slack each side
    for rounding), so that a box's rows are searched there instead of in the whole level
    (a part's box is a small share of its tile)."""
    if not (math.isfinite(x_low) and math.isfinite(x_high)) or keys.size == 0:
        return 0, int(keys.size)
    shift = 2 * CELL_BITS
    top = 1 << CELL_BITS
    low = min(max(math.floor(x_low / voxel_m) - 1 + CELL_OFFSET, 0), top)
    high = min(max(math.floor(x_high / voxel_m) + 2 + CELL_OFFSET, 0), top)
    first, last = np.searchsorted(keys, [low << shift, high << shift])
    return int(first), int(last)


def _nearest_sides(xy: NDArray[np.float64], box: NDArray[np.float64]) -> NDArray[np.int64]:
    """Which side of ``box`` (``x_low, x_high, y_low, y_high``: 0-3) each point is nearest,
    and which of :data:`_SIDE_PIECES` equal pieces of that side: ``side * pieces + piece``
    (a piece's few far-reaching queries do not widen the whole side's band)."""
    distances = np.stack(
        [xy[:, 0] - box[0], box[1] - xy[:, 0], xy[:, 1] - box[2], box[3] - xy[:, 1]], axis=1
    )
    sides = np.argmin(distances, axis=1).astype(np.int64)
    along = np.where(sides < 2, xy[:, 1], xy[:, 0])  # the coordinate along the side
    low = np.where(sides < 2, box[2], box[0])
    length = np.maximum(np.where(sides < 2, box[3] - box[2], box[1] - box[0]), 1e-12)
    piece = np.clip(np.floor((along - low) / length * _SIDE_PIECES), 0, _SIDE_PIECES - 1)
    groups: NDArray[np.int64] = sides * _SIDE_PIECES + piece.astype(np.int64)
    return groups


def _ball_box(centres: NDArray[np.float64], radius: NDArray[np.float64]) -> NDArray[np.float64]:
    """The box (``x_low, x_high, y_low, y_high``) holding the discs of ``radius`` around
    ``centres``."""
    return np.array(
        [
            (centres[:, 0] - radius).min(),
            (centres[:, 0] + radius).max(),
            (centres[:, 1] - radius).min(),
            (centres[:, 1] + radius).max(),
        ]
    )
