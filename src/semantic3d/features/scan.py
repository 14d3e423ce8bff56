"""Features of a whole scan streamed from disk: in memory when small, tile by tile when large.

:func:`iter_scan_features` is the one entry point training and prediction use
(:func:`map_scan_features` is the same with the tiles of a large scan described on several
threads at once). Scans up to ``max_points_in_memory`` points are described whole by
:func:`~semantic3d.features.multiscale.compute_multiscale_features`; larger ones go
through :class:`~semantic3d.features.tiling.TiledScan`. Both give the same rows (tested),
so the switch changes memory and speed, never results.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from itertools import chain
from pathlib import Path
from typing import TypeVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from semantic3d.core.errors import ShapeError
from semantic3d.core.pointcloud import PointCloud
from semantic3d.features.config import FeatureConfig
from semantic3d.features.multiscale import (
    FeatureTable,
    RowMap,
    compute_multiscale_features,
    map_table_rows,
)
from semantic3d.features.tiling import DEFAULT_TILE_SIZE_M, TiledScan, TileFeatures

R = TypeVar("R")


@dataclass(frozen=True, slots=True)
class FeatureBlock:
    """Feature rows of some points of a scan.

    Attributes:
        point_indices: ``(m,)`` int64 indices of the points in the scan, ascending.
        table: rows of those points (``table.point_row`` aligned with ``point_indices``).
        labels: ``(m,)`` uint8 label values when the scan came with labels.
        n_scan_points: points in the whole scan (known once streaming has finished).
        tiled: whether the scan was processed tile by tile.
    """

    point_indices: NDArray[np.int64]
    table: FeatureTable
    labels: NDArray[np.uint8] | None
    n_scan_points: int
    tiled: bool


def iter_scan_features(
    chunks: Iterable[PointCloud],
    *,
    config: FeatureConfig,
    select: ArrayLike | None = None,
    max_points_in_memory: int = 4_000_000,
    tile_size_m: float = DEFAULT_TILE_SIZE_M,
    workdir: str | Path | None = None,
) -> Iterator[FeatureBlock]:
    """Feature blocks covering the selected points of a streamed scan (tiles in order).

    Args:
        chunks: the scan's point chunks in file order.
        config: feature settings.
        select: global indices of the points to describe (default all).
        max_points_in_memory: above this many points the scan is tiled.
        tile_size_m: tile edge when tiled.
        workdir: where the scratch folder of the tiles is made (removed afterwards).
    """
    return map_scan_features(
        chunks,
        _same,
        config=config,
        select=select,
        max_points_in_memory=max_points_in_memory,
        tile_size_m=tile_size_m,
        workdir=workdir,
        n_threads=1,
    )


def _same(block: FeatureBlock) -> FeatureBlock:
    return block


def map_scan_features(
    chunks: Iterable[PointCloud],
    function: Callable[[FeatureBlock], R],
    *,
    config: FeatureConfig,
    select: ArrayLike | None = None,
    max_points_in_memory: int = 4_000_000,
    tile_size_m: float = DEFAULT_TILE_SIZE_M,
    workdir: str | Path | None = None,
    n_threads: int | None = None,
    row_map: RowMap | None = None,
) -> Iterator[R]:
    """``function(block)`` for every feature block of a streamed scan (those of
    :func:`iter_scan_features`).

    A tiled scan's tiles are described and passed to ``function`` on ``n_threads`` threads
    at once (default the thread budget, :mod:`semantic3d.core.threads`; see
    :meth:`~semantic3d.features.tiling.TiledScan.map_tiles`): results come as tiles finish,
    in no fixed order (one thread: tiles in order), each the same as alone. ``function``
    must be safe to call from several threads at once. With ``row_map`` every block's
    rows reach ``function`` mapped (:attr:`~semantic3d.features.multiscale.FeatureTable.mapped`):
    a tile's as they are made, never its whole table at once
    (:meth:`~semantic3d.features.tiling.TiledScan.tile_features`).
    """
    stream = iter(chunks)
    held: list[PointCloud] = []
    held_points = 0
    for chunk in stream:
        held.append(chunk)
        held_points += chunk.n_points
        if held_points > max_points_in_memory:
            with TiledScan(
                chain(held, stream), config=config, tile_size_m=tile_size_m, workdir=workdir
            ) as scan:
                held.clear()

                def describe(tile: TileFeatures, scan: TiledScan = scan) -> R:
                    block = FeatureBlock(
                        tile.point_indices, tile.table, tile.labels, scan.n_points, tiled=True
                    )
                    return function(block)

                # a block carries no positions: a tile's are not copied (24 bytes a point)
                if n_threads == 1:
                    for tile in scan.iter_features(select=select, row_map=row_map, positions=False):
                        yield describe(tile)
                else:
                    yield from scan.map_tiles(
                        describe,
                        select=select,
                        n_threads=n_threads,
                        row_map=row_map,
                        positions=False,
                    )
            return
    if held_points == 0:
        raise ShapeError("cannot compute features of an empty scan")
    cloud = held[0] if len(held) == 1 else PointCloud.concatenate(held)
    held.clear()
    indices = (
        np.arange(cloud.n_points, dtype=np.int64)
        if select is None
        else np.unique(np.asarray(select, dtype=np.int64))
    )
    if indices.size == 0:
        return
    table = compute_multiscale_features(cloud, config=config, point_indices=indices)
    if row_map is not None:
        table = map_table_rows(table, row_map)
    labels = None if cloud.labels is None else cloud.labels[indices]
    yield function(FeatureBlock(indices, table, labels, cloud.n_points, tiled=False))
