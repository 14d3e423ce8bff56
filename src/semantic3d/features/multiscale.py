"""Multi-scale features of a point cloud held in memory (Hackel et al. 2016).

Build the voxel pyramid, then at every level find the k nearest level points of each
query and compute the covariance, moment and height features (plus colour / intensity
when asked). Queries are the level voxels containing the requested points (default) or
the requested points themselves (``FeatureConfig.per_point``). For scans too large for
memory, :mod:`semantic3d.features.tiling` produces identical rows tile by tile.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numba
import numpy as np
from numpy.typing import ArrayLike, NDArray

from semantic3d.core.errors import ShapeError
from semantic3d.core.pointcloud import PointCloud
from semantic3d.core.threads import take_free_threads
from semantic3d.features._row_kernels import copy_rows, distinct_values, put_rows, take_rows
from semantic3d.features.attributes import compute_attribute_features
from semantic3d.features.config import FeatureConfig
from semantic3d.features.covariance import (
    N_COVARIANCE_COLUMNS,
    geometry_kernel,
)
from semantic3d.features.cylinders import compute_cylinder_features
from semantic3d.features.height import N_HEIGHT_COLUMNS
from semantic3d.features.neighbourhoods import LevelIndex
from semantic3d.features.pyramid import PyramidLevel, VoxelPyramid, build_pyramid, grid_origin


@dataclass(frozen=True, slots=True)
class FeatureTable:
    """Feature rows and the row of every requested point.

    In voxel mode the points of one level-0 voxel share a row (classify rows, then
    ``labels_of_rows[point_row]``); in per-point mode every point has its own row.

    Attributes:
        names: column names (``planarity@0.100m``), level-major.
        values: ``(n_rows, n_features)`` float32.
        point_row: ``(n_points,)`` int64 row of each requested point, in request order.
        neighbours: in voxel mode, ``(n_rows, k)`` int64: the rows of the ``k`` nearest
            level-0 voxels of every row's voxel, nearest first (the level-0 features' own
            canonical k-NN, so the voxel itself comes first), ``-1`` where that voxel has no
            row here (its points were not requested, or lie in another tile); None in
            per-point mode. A graph over the rows for free (the context step's).
        mapped: the rows passed through a caller's ``row_map`` as they were made, one
            result row per feature row (e.g. a classifier's class probabilities), where
            the caller asked for it; ``values`` then has no columns (``(n_rows, 0)``): the
            feature rows were never held all at once.
    """

    names: tuple[str, ...]
    values: NDArray[np.float32]
    point_row: NDArray[np.int64]
    neighbours: NDArray[np.int64] | None = None
    mapped: NDArray[Any] | None = None

    @property
    def n_rows(self) -> int:
        """Number of feature rows."""
        return int(self.values.shape[0])

    def point_values(self) -> NDArray[np.float32]:
        """``(n_points, n_features)``: the row of every requested point (a copy)."""
        return self.values[self.point_row]


RowMap = Callable[[NDArray[np.float32]], NDArray[Any]]
"""A map of feature rows ``(m, n_features)`` to ``m`` result rows, row by row (a row's
result depends on that row alone), applied to blocks of a table's rows as they are made."""

ROW_BLOCK = 1 << 16
"""Feature rows made and mapped at a time when a caller maps them (about 40 MB at the
default 153 columns): a tile's table of a million rows is never held whole."""


def map_rows(
    n_rows: int,
    n_columns: int,
    fill: Callable[[int, NDArray[np.float32]], None],
    row_map: RowMap,
) -> NDArray[Any]:
    """``row_map`` of ``n_rows`` feature rows made :data:`ROW_BLOCK` at a time:
    ``fill(start, out)`` writes rows ``start .. start + len(out)`` into ``out`` (one
    buffer, reused), and the results go one after another into the array returned."""
    block = np.empty((min(ROW_BLOCK, n_rows), n_columns), np.float32)
    mapped: NDArray[Any] | None = None
    for start in range(0, n_rows, ROW_BLOCK):
        part = block[: min(ROW_BLOCK, n_rows - start)]
        fill(start, part)
        result = row_map(part)
        if mapped is None:
            mapped = np.empty((n_rows, *result.shape[1:]), result.dtype)
        mapped[start : start + part.shape[0]] = result
    return row_map(block[:0]) if mapped is None else mapped


def map_table_rows(table: FeatureTable, row_map: RowMap) -> FeatureTable:
    """``table`` with its rows mapped by ``row_map`` (:func:`map_rows`) into
    :attr:`FeatureTable.mapped`, its values dropped."""
    values = table.values

    def fill(start: int, out: NDArray[np.float32]) -> None:
        out[:] = values[start : start + out.shape[0]]

    return FeatureTable(
        table.names,
        np.empty((table.n_rows, 0), np.float32),
        table.point_row,
        table.neighbours,
        mapped=map_rows(table.n_rows, values.shape[1], fill, row_map),
    )


def attribute_columns(cloud: PointCloud, config: FeatureConfig) -> NDArray[np.float64] | None:
    """Per-point values averaged in the pyramid: ``r g b`` and/or intensity, or None."""
    parts: list[NDArray[np.float64]] = []
    if config.colour:
        parts.append(cloud.rgb.astype(np.float64))
    if config.intensity:
        parts.append(cloud.intensity.astype(np.float64)[:, None])
    return np.hstack(parts) if parts else None


def build_cloud_pyramid(
    cloud: PointCloud, *, config: FeatureConfig, origin: ArrayLike | None = None
) -> VoxelPyramid:
    """The voxel pyramid of ``cloud`` for ``config`` (origin from its first point by default)."""
    if cloud.n_points == 0:
        raise ShapeError("cannot compute features of an empty point cloud")
    anchor = (
        grid_origin(cloud.xyz[0], coarsest_voxel_size_m=config.coarsest_voxel_size_m)
        if origin is None
        else np.asarray(origin, dtype=np.float64)
    )
    return build_pyramid(
        cloud.xyz,
        base_voxel_size_m=config.base_voxel_size_m,
        n_levels=config.n_levels,
        origin=anchor,
        attributes=attribute_columns(cloud, config),
    )


def compute_level_features(
    index: LevelIndex,
    attributes: NDArray[np.float64],
    queries: NDArray[np.float64],
    *,
    config: FeatureConfig,
    level: int,
    out: NDArray[np.float32] | None = None,
    neighbours: NDArray[np.int64] | None = None,
) -> tuple[NDArray[np.float32], NDArray[np.float64]]:
    """Features of ``queries`` against one level; also how far each row looked.

    Args:
        index: the level's points and keys.
        attributes: ``(n_points, a)`` per-voxel attribute means of the level.
        queries: ``(m, 3)`` float64 query points relative to the grid origin.
        config: feature settings (k, height features, colour, intensity).
        level: the level's number (0 finest), which sets the cylinder radius.
        out: optional ``(m, n_level_features)`` float32 destination (may be a column
            slice of a wider table).
        neighbours: optional ``(m, min(k, n_points))`` int64 destination for every query's
            neighbours (indices into ``index``'s points, canonical order).

    Returns:
        ``(m, n_level_features)`` float32 block (``out`` when given) and ``(m,)`` reach:
        the k-th neighbour distance, or the cylinder radius when larger. Every level point
        that can change a row lies within its reach horizontally (the tiles' halo test).
    """
    queries = np.ascontiguousarray(queries, dtype=np.float64)
    width = len(config.level_feature_names)
    if out is None:
        out = np.empty((queries.shape[0], width), np.float32)
    if out.shape != (queries.shape[0], width):
        raise ShapeError(f"out: expected ({queries.shape[0]}, {width}), found {out.shape}")
    # in a map's last tasks each step goes on with the threads the others left
    take_free_threads()
    found = index.query(queries, k=config.k_neighbours)
    if neighbours is not None:
        if neighbours.shape != found.indices.shape:
            raise ShapeError(
                f"neighbours: expected {found.indices.shape}, found {neighbours.shape}"
            )
        copy_rows(found.indices, neighbours)
    column = N_COVARIANCE_COLUMNS + (N_HEIGHT_COLUMNS if config.spherical_height else 0)
    # The kernels always get C-contiguous arrays of one dtype: every other layout would be
    # another compilation (~10 s) on first use. A column slice goes through a block.
    indices = np.ascontiguousarray(found.indices, dtype=np.uint32)
    target = out[:, :column]
    if out.flags.c_contiguous:  # the kernels write the first columns of each row
        block = out  # its pages first touched by the kernels' threads, not copied into
    elif target.flags.c_contiguous:
        block = target
    else:
        block = np.empty(target.shape, np.float32)
    take_free_threads()
    geometry_kernel(
        index.xyz, indices, queries, block, config.spherical_height, numba.get_num_threads()
    )
    if block is not target and block is not out:
        copy_rows(block, target)
    reach = reach_of_kth(found.kth_distance, config, level)
    if config.cylinders:
        radius_m = config.cylinder_radius_m(level)
        width = len(config.cylinder_features)
        take_free_threads()
        cylinders = compute_cylinder_features(
            index.xyz, queries, radius_m=radius_m, features=config.cylinder_features
        )
        copy_rows(cylinders, out[:, column : column + width])
        column += width
    if config.colour or config.intensity:
        out[:, column:] = compute_attribute_features(
            attributes, found.indices, colour=config.colour, intensity=config.intensity
        )
    return out, reach


def level_reach(
    index: LevelIndex, queries: NDArray[np.float64], *, config: FeatureConfig, level: int
) -> NDArray[np.float64]:
    """The reach :func:`compute_level_features` gives ``queries`` (the k-th neighbour
    distance, or the cylinder radius when larger), without their features."""
    queries = np.ascontiguousarray(queries, dtype=np.float64)
    return reach_of_kth(index.query(queries, k=config.k_neighbours).kth_distance, config, level)


def reach_of_kth(
    kth: NDArray[np.float64], config: FeatureConfig, level: int
) -> NDArray[np.float64]:
    """The reach of rows whose k-th neighbour lies at ``kth``: that distance, or the
    level's cylinder radius when larger."""
    if config.cylinders:
        reach: NDArray[np.float64] = np.maximum(kth, config.cylinder_radius_m(level))
        return reach
    return kth


def compute_multiscale_features(
    cloud: PointCloud,
    *,
    config: FeatureConfig,
    point_indices: ArrayLike | None = None,
    origin: ArrayLike | None = None,
) -> FeatureTable:
    """Multi-scale features of the points of ``cloud`` (all, or ``point_indices``).

    Args:
        cloud: the whole scan (or any cloud that fits in memory).
        config: pyramid and feature settings.
        point_indices: points to describe (default all); training asks for a sample.
        origin: grid anchor; default :func:`~semantic3d.features.pyramid.grid_origin` of
            the first point, as the tiled path uses.
    """
    pyramid = build_cloud_pyramid(cloud, config=config, origin=origin)
    wanted = (
        np.arange(cloud.n_points, dtype=np.int64)
        if point_indices is None
        else np.asarray(point_indices, dtype=np.int64).reshape(-1)
    )
    if wanted.size and (wanted.min() < 0 or wanted.max() >= cloud.n_points):
        raise ShapeError(f"point_indices: expected values in 0..{cloud.n_points - 1}")
    width = len(config.level_feature_names)
    if config.per_point:
        queries = cloud.xyz[wanted] - pyramid.origin
        values = np.empty((wanted.size, config.n_features), np.float32)
        for level_number, level in enumerate(pyramid.levels):
            index = LevelIndex(level.xyz, level.keys)
            columns = values[:, level_number * width : (level_number + 1) * width]
            compute_level_features(
                index, level.attributes, queries, config=config, level=level_number, out=columns
            )
        point_row = np.arange(wanted.size, dtype=np.int64)
        return FeatureTable(config.feature_names, values, point_row)

    voxels, point_row = distinct_voxels(pyramid.point_voxel[wanted])
    values = np.empty((voxels.size, config.n_features), np.float32)
    base = pyramid.levels[0]
    neighbours = np.empty((voxels.size, min(config.k_neighbours, base.n_voxels)), np.int64)
    ancestor = voxels
    for level_number, level in enumerate(pyramid.levels):
        if level_number:
            ancestor = pyramid.levels[level_number - 1].parent[ancestor]
        index = LevelIndex(level.xyz, level.keys)

        def compute(
            needed: NDArray[np.int64],
            out: NDArray[np.float32],
            index: LevelIndex = index,
            level: PyramidLevel = level,
            number: int = level_number,
        ) -> None:
            # every voxel of the level (the usual case): query the level's own array,
            # whose float32 copy the index already holds
            queries = level.xyz if needed.size == level.n_voxels else take_rows(level.xyz, needed)
            compute_level_features(
                index,
                level.attributes,
                queries,
                config=config,
                level=number,
                out=out,
                # level 0 holds one row per voxel, in row order: keep its k-NN
                neighbours=neighbours if number == 0 else None,
            )

        fill_level_columns(
            values[:, level_number * width : (level_number + 1) * width], ancestor, compute
        )
    if voxels.size != base.n_voxels:  # some voxels have no row: renumber as rows
        row_of_voxel = np.full(base.n_voxels, -1, np.int64)
        row_of_voxel[voxels] = np.arange(voxels.size)
        neighbours = row_of_voxel[neighbours]
    return FeatureTable(config.feature_names, values, point_row, neighbours)


def fill_level_columns(
    columns: NDArray[np.float32],
    voxel_of_row: NDArray[np.int64],
    compute: Callable[[NDArray[np.int64], NDArray[np.float32]], None],
) -> None:
    """Set ``columns[i]`` to the features of level voxel ``voxel_of_row[i]``.

    ``compute(voxels, out)`` fills ``out`` with the features of distinct, sorted ``voxels``;
    it runs once per voxel, and its rows are copied to every row of that voxel.
    """
    needed, inverse = level_rows(voxel_of_row)
    if inverse is None:
        # one row per voxel, in voxel order (level 0 in voxel mode): fill in place
        compute(needed, columns)
        return
    block = np.empty((needed.size, columns.shape[1]), np.float32)
    compute(needed, block)
    put_rows(block, inverse, columns, 0)  # columns[:] = block[inverse]


def level_rows(
    voxel_of_row: NDArray[np.int64],
) -> tuple[NDArray[np.int64], NDArray[np.int64] | None]:
    """What :func:`fill_level_columns` computes, for a caller that computes it later:
    the distinct sorted voxels of ``voxel_of_row``, and the inverse whose
    ``put_rows(block, inverse, columns, 0)`` copies their rows to every row (None when the
    rows already are their voxels in order: the columns are filled in place)."""
    needed, inverse, in_order = _distinct(voxel_of_row)
    return needed, None if in_order else inverse


def distinct_voxels(
    voxel_of_row: NDArray[np.int64],
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """``np.unique(voxel_of_row, return_inverse=True)`` for non-negative voxel indices,
    by marking a table as large as the largest index instead of sorting (linear time, on
    every thread)."""
    needed, inverse, _ = _distinct(voxel_of_row)
    return needed, inverse


def _distinct(
    voxel_of_row: NDArray[np.int64],
) -> tuple[NDArray[np.int64], NDArray[np.int64], bool]:
    """:func:`distinct_voxels` and whether the rows already are their voxels in order."""
    if voxel_of_row.size == 0:
        return np.empty(0, np.int64), np.empty(0, np.int64), True
    needed, inverse, in_order = distinct_values(np.ascontiguousarray(voxel_of_row, dtype=np.int64))
    return needed, inverse, bool(in_order)
