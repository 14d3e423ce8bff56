"""Multi-scale features of scans larger than memory, tile by tile, equal to the whole-scan rows.

:class:`TiledScan` streams point chunks once into square columns ("tiles") on disk, then
builds each tile's voxel pyramid, then computes features tile by tile. Tiles are aligned to
the coarsest voxel grid, so every voxel of every level lies in exactly one tile and each
tile's pyramid holds exactly the whole scan's voxels. At level ``l`` a tile's queries look
for neighbours among the level-``l`` points of the tile plus a *halo* gathered from its
neighbours. The halo is per level (fine levels need centimetres, coarse ones metres) and
adaptive: a query is accepted only when its k-th neighbour is closer than the halo's edge
(so no point outside could be nearer); the others are asked again in a box holding the
ball of their k-th distance. In voxel mode the coarsest levels, which hold few voxels, are
described once over the whole scan instead. With the canonical neighbour order of
:mod:`~semantic3d.features.neighbourhoods`, rows are bit-for-bit those of
:func:`~semantic3d.features.multiscale.compute_multiscale_features`.

Peak memory is set by the densest tile and its halo, not by the scan size; disk use is
about 40 bytes per point.
"""

from __future__ import annotations

import itertools
import logging
import math
import shutil
import tempfile
from collections import OrderedDict
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from semantic3d.core.errors import ShapeError
from semantic3d.core.pointcloud import PointCloud
from semantic3d.features.config import ConfigError, FeatureConfig
from semantic3d.features.multiscale import (
    FeatureTable,
    attribute_columns,
    compute_level_features,
    distinct_voxels,
    fill_level_columns,
)
from semantic3d.features.neighbourhoods import LevelIndex
from semantic3d.features.pyramid import build_pyramid, compute_cells, grid_origin

logger = logging.getLogger(__name__)

DEFAULT_TILE_SIZE_M = 25.6
"""Default tile edge (rounded up to a multiple of the coarsest voxel)."""

_SAFETY_M = 1e-3
"""Margin kept between a k-th neighbour and the halo edge (covers the float32 search)."""

_FIRST_HALO_VOXELS = 4.0
"""First halo of a level, in voxels of that level (k = 10 on a surface needs ~2)."""

_SLACK_M = 1e-6
"""Points may sit this far outside their tile's edges (rounding of cell indices)."""

Tile = tuple[int, int]


@dataclass(frozen=True, slots=True)
class TileFeatures:
    """Feature rows of the selected points of one tile.

    Attributes:
        tile: ``(ix, iy)`` tile index.
        point_indices: ``(m,)`` int64 indices of the points in the whole scan, ascending.
        table: rows for those points (``table.point_row`` aligned with ``point_indices``).
        labels: ``(m,)`` uint8 label values when the chunks carried labels, else None.
    """

    tile: Tile
    point_indices: NDArray[np.int64]
    table: FeatureTable
    labels: NDArray[np.uint8] | None


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
        self.origin: NDArray[np.float64] | None = None
        self.n_points = 0
        self.has_labels: bool | None = None
        self._counts: dict[Tile, int] = {}
        self._halo_hint = [0.0] * config.n_levels
        self._level_sizes = [0] * config.n_levels
        self._whole: dict[int, tuple[NDArray[np.int64], NDArray[np.float32]] | None] = {}
        self.whole_level_points = whole_level_points
        self.cache_bytes = cache_bytes
        self._cache: OrderedDict[Tile, dict[str, NDArray[Any]]] = OrderedDict()
        self._dtype: np.dtype[Any] = np.dtype([])
        self._tile_low = np.zeros(2)
        self._tile_high = np.zeros(2)
        self._cache_bytes = 0
        try:
            self._spill(chunks)
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
        shutil.rmtree(self.workdir, ignore_errors=True)

    @property
    def tiles(self) -> tuple[Tile, ...]:
        """Non-empty tiles, sorted."""
        return tuple(sorted(self._counts))

    def tile_points(self, tile: Tile) -> int:
        """Number of points in ``tile``."""
        return self._counts.get(tile, 0)

    # -- pass 1: spill ---------------------------------------------------------------------
    def _path(self, tile: Tile, name: str) -> Path:
        return self.workdir / f"{tile[0]}_{tile[1]}.{name}"

    def _record_dtype(self, chunk: PointCloud) -> np.dtype[Any]:
        fields: list[tuple[Any, ...]] = [("xyz", np.float64, (3,)), ("idx", np.int64)]
        n_attributes = 3 * self.config.colour + self.config.intensity
        if n_attributes:
            fields.append(("attr", np.float64, (n_attributes,)))
        if chunk.labels is not None:
            fields.append(("lab", np.uint8))
        return np.dtype(fields)

    def _spill(self, chunks: Iterable[PointCloud]) -> None:
        config = self.config
        for chunk in chunks:
            if chunk.n_points == 0:
                continue
            if self.origin is None:
                self.origin = grid_origin(
                    chunk.xyz[0], coarsest_voxel_size_m=config.coarsest_voxel_size_m
                )
                self.has_labels = chunk.labels is not None
                self._dtype = self._record_dtype(chunk)
            if (chunk.labels is not None) != self.has_labels:
                raise ShapeError("chunks: expected labels on every chunk or on none")
            cells = compute_cells(
                chunk.xyz, origin=self.origin, voxel_size_m=config.base_voxel_size_m
            )
            tile_xy = cells[:, :2] // self.tile_cells
            records = np.empty(chunk.n_points, self._dtype)
            records["xyz"] = chunk.xyz
            records["idx"] = np.arange(self.n_points, self.n_points + chunk.n_points)
            attributes = attribute_columns(chunk, config)
            if attributes is not None:
                records["attr"] = attributes
            if chunk.labels is not None:
                records["lab"] = chunk.labels
            order = np.lexsort((tile_xy[:, 1], tile_xy[:, 0]))  # stable: file order kept
            sorted_xy = tile_xy[order]
            starts = np.flatnonzero(np.any(sorted_xy[1:] != sorted_xy[:-1], axis=1)) + 1
            bounds = np.concatenate(([0], starts, [order.size]))
            for begin, end in itertools.pairwise(bounds):
                tile = (int(sorted_xy[begin, 0]), int(sorted_xy[begin, 1]))
                with self._path(tile, "pts").open("ab") as stream:
                    stream.write(records[order[begin:end]].tobytes())
                self._counts[tile] = self._counts.get(tile, 0) + int(end - begin)
            self.n_points += chunk.n_points
        if self.origin is None:
            raise ShapeError("cannot tile an empty scan")
        tiles = np.array(self.tiles)
        self._tile_low = tiles.min(axis=0) * self.tile_size_m - _SLACK_M
        self._tile_high = (tiles.max(axis=0) + 1) * self.tile_size_m + _SLACK_M
        logger.info("spilled %d points into %d tiles", self.n_points, len(self._counts))

    def _load_points(self, tile: Tile) -> NDArray[np.void]:
        records: NDArray[np.void] = np.fromfile(self._path(tile, "pts"), self._dtype)
        return records

    # -- pass 2: pyramids ------------------------------------------------------------------
    def _build_pyramids(self) -> None:
        assert self.origin is not None  # set by _spill
        config = self.config
        for tile in self.tiles:
            records = self._load_points(tile)
            pyramid = build_pyramid(
                records["xyz"],
                base_voxel_size_m=config.base_voxel_size_m,
                n_levels=config.n_levels,
                origin=self.origin,
                attributes=records["attr"] if "attr" in (self._dtype.names or ()) else None,
            )
            arrays: dict[str, NDArray[Any]] = {"voxel": pyramid.point_voxel}
            for number, level in enumerate(pyramid.levels):
                self._level_sizes[number] += level.n_voxels
                arrays[f"xyz{number}"] = level.xyz
                arrays[f"keys{number}"] = level.keys
                arrays[f"attr{number}"] = level.attributes
                arrays[f"parent{number}"] = level.parent
            with self._path(tile, "pyr.npz").open("wb") as stream:
                np.savez(stream, **arrays)  # type: ignore[arg-type]

    def _pyramid(self, tile: Tile) -> dict[str, NDArray[Any]]:
        """A tile's pyramid arrays, through a byte-bounded LRU cache (halos reread them)."""
        cached = self._cache.get(tile)
        if cached is not None:
            self._cache.move_to_end(tile)
            return cached
        with np.load(self._path(tile, "pyr.npz")) as stored:
            arrays = {name: stored[name] for name in stored.files}
        self._cache[tile] = arrays
        self._cache_bytes += sum(a.nbytes for a in arrays.values())
        while self._cache_bytes > self.cache_bytes and len(self._cache) > 1:
            _, evicted = self._cache.popitem(last=False)
            self._cache_bytes -= sum(a.nbytes for a in evicted.values())
        return arrays

    # -- pass 3: features ------------------------------------------------------------------
    def iter_features(self, *, select: ArrayLike | None = None) -> Iterator[TileFeatures]:
        """Feature rows tile by tile (tiles in sorted order, points ascending inside).

        Args:
            select: global indices of the points to describe (default all); tiles without
                a selected point are skipped.
        """
        wanted = None if select is None else np.unique(np.asarray(select, dtype=np.int64))
        for tile in self.tiles:
            records = self._load_points(tile)
            keep = (
                np.ones(records.size, bool)
                if wanted is None
                else np.isin(records["idx"], wanted, assume_unique=True)
            )
            if not keep.any():
                continue
            labels = records["lab"][keep] if self.has_labels else None
            table = self._tile_table(tile, records["xyz"][keep], np.flatnonzero(keep))
            yield TileFeatures(tile, records["idx"][keep], table, labels)

    def _tile_table(
        self, tile: Tile, xyz: NDArray[np.float64], local: NDArray[np.int64]
    ) -> FeatureTable:
        assert self.origin is not None
        config = self.config
        width = len(config.level_feature_names)
        pyramid = self._pyramid(tile)
        if config.per_point:
            queries = xyz - self.origin
            values = np.empty((queries.shape[0], config.n_features), np.float32)
            for number in range(config.n_levels):
                values[:, number * width : (number + 1) * width] = self._exact_level(
                    tile, number, queries
                )
            return FeatureTable(
                config.feature_names, values, np.arange(queries.shape[0], dtype=np.int64)
            )
        voxels, point_row = distinct_voxels(pyramid["voxel"][local])
        values = np.empty((voxels.size, config.n_features), np.float32)
        ancestor = voxels
        for number in range(config.n_levels):
            if number:
                ancestor = pyramid[f"parent{number - 1}"][ancestor]

            def compute(
                needed: NDArray[np.int64], out: NDArray[np.float32], number: int = number
            ) -> None:
                whole = self._whole_level(number)
                if whole is None:
                    out[:] = self._exact_level(tile, number, pyramid[f"xyz{number}"][needed])
                else:
                    keys, rows = whole
                    out[:] = rows[np.searchsorted(keys, pyramid[f"keys{number}"][needed])]

            fill_level_columns(values[:, number * width : (number + 1) * width], ancestor, compute)
        return FeatureTable(config.feature_names, values, point_row)

    def _whole_level(self, number: int) -> tuple[NDArray[np.int64], NDArray[np.float32]] | None:
        """Features of every voxel of a small level, computed once over the whole level.

        Coarse levels hold few voxels; describing them in one pass needs no halo and saves
        a k-NN call per tile. Levels are taken from the coarsest down while their voxels
        add up to at most ``whole_level_points``, so the rows kept stay bounded. Returns
        ``(sorted keys, rows)``, or None for the levels that go tile by tile.
        """
        if number in self._whole:
            return self._whole[number]
        result = None
        if sum(self._level_sizes[number:]) <= self.whole_level_points:
            box = np.array([-np.inf, np.inf, -np.inf, np.inf])
            xyz, keys, attributes = self._gather(number, box)
            order = np.argsort(keys)
            xyz, keys, attributes = xyz[order], keys[order], attributes[order]
            rows, _ = compute_level_features(
                LevelIndex(xyz, keys), attributes, xyz, config=self.config
            )
            result = (keys, rows)
        self._whole[number] = result
        return result

    def _exact_level(
        self, tile: Tile, number: int, queries: NDArray[np.float64]
    ) -> NDArray[np.float32]:
        """Level ``number`` features of ``queries`` (in ``tile``), widening the halo until exact.

        First the tile plus a halo learnt from the previous tile; a query whose k-th
        neighbour lies beyond the halo's edge is asked again in a box containing the ball
        of that radius (the k-th distance within a subset bounds the true one), which is
        then exact; a subset with fewer than k points doubles the box.
        """
        config = self.config
        size = self.tile_size_m
        out = np.empty((queries.shape[0], len(config.level_feature_names)), np.float32)
        pending = np.arange(queries.shape[0])
        halo = max(_FIRST_HALO_VOXELS * config.voxel_sizes_m[number], self._halo_hint[number])
        box = np.array(
            [
                tile[0] * size - halo,
                (tile[0] + 1) * size + halo,
                tile[1] * size - halo,
                (tile[1] + 1) * size + halo,
            ]
        )
        first = True
        while pending.size:
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
            asked = queries[pending]
            block, kth = compute_level_features(
                LevelIndex(xyz, keys), attributes, asked, config=config
            )
            enough = xyz.shape[0] >= config.k_neighbours
            if infinite.all():
                exact = np.ones(pending.size, bool)
            else:
                edge = _distance_to_edge(asked, box, infinite)
                exact = enough & (kth * (1.0 + 1e-6) + _SAFETY_M < edge)
            out[pending[exact]] = block[exact]
            if first and enough:  # the next tile starts with a halo most queries need
                self._halo_hint[number] = 1.1 * float(np.quantile(kth, 0.95))
                first = False
            pending = pending[~exact]
            if pending.size:
                if enough:
                    radius = kth[~exact] * (1.0 + 1e-6) + 2.0 * _SAFETY_M
                else:
                    radius = np.full(pending.size, box[1] - box[0] + box[3] - box[2])
                rest = asked[~exact]
                box = np.array(
                    [
                        (rest[:, 0] - radius).min(),
                        (rest[:, 0] + radius).max(),
                        (rest[:, 1] - radius).min(),
                        (rest[:, 1] + radius).max(),
                    ]
                )
        return out

    def _gather(
        self, number: int, box: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.int64], NDArray[np.float64]]:
        """Level ``number`` points of every tile that lie inside ``box``."""
        size = self.tile_size_m
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
        if (x_high - x_low + 1) * (y_high - y_low + 1) <= len(self._counts):
            candidates: Iterable[Tile] = (
                (ix, iy) for ix in range(x_low, x_high + 1) for iy in range(y_low, y_high + 1)
            )
        else:
            candidates = self.tiles
        parts_xyz, parts_keys, parts_attr = [], [], []
        for other in candidates:
            if other not in self._counts or not (
                x_low <= other[0] <= x_high and y_low <= other[1] <= y_high
            ):
                continue
            pyramid = self._pyramid(other)
            xyz = pyramid[f"xyz{number}"]
            inside = (
                (xyz[:, 0] >= box[0])
                & (xyz[:, 0] <= box[1])
                & (xyz[:, 1] >= box[2])
                & (xyz[:, 1] <= box[3])
            )
            parts_xyz.append(xyz[inside])
            parts_keys.append(pyramid[f"keys{number}"][inside])
            parts_attr.append(pyramid[f"attr{number}"][inside])
        return np.concatenate(parts_xyz), np.concatenate(parts_keys), np.concatenate(parts_attr)


def _distance_to_edge(
    queries: NDArray[np.float64], box: NDArray[np.float64], infinite: NDArray[np.bool_]
) -> NDArray[np.float64]:
    """Horizontal distance from each query to the nearest closed edge of ``box``."""
    gaps = np.column_stack(
        [
            queries[:, 0] - box[0],
            box[1] - queries[:, 0],
            queries[:, 1] - box[2],
            box[3] - queries[:, 1],
        ]
    )
    gaps[:, infinite] = np.inf
    distances: NDArray[np.float64] = gaps.min(axis=1)
    return distances
