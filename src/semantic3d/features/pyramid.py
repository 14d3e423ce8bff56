"""The multi-scale voxel pyramid (Hackel, Wegner & Schindler 2016, section 3.1).

Level 0 is a voxel-grid filter of the points at ``base_voxel_size_m``: one representative
point per occupied voxel, the centroid of its points. Level ``l + 1`` filters level ``l``
with voxels twice as large, the representative being the mean of its child centroids
(the filter applied repeatedly, as in the paper; every child counts once, so dense
patches do not dominate coarse levels).

All grids are anchored at one ``origin`` that is a multiple of the coarsest voxel size, so
voxels of every level nest in the voxels of the next and in any tile aligned to the
coarsest grid. Cells are integer coordinates relative to that origin; a voxel's *key*
packs its three cells into one int64 (21 bits each), which orders and identifies it.
Every sum runs in a fixed order (points in input order within a voxel, children in key
order), so a pyramid built from a tile equals the same voxels of the whole-scan pyramid
bit for bit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from numpy.typing import ArrayLike, NDArray

from semantic3d.core.errors import ShapeError
from semantic3d.spatial.voxels import (
    ExtentError,
    compute_cells,
    grid_origin,
    pack_keys,
)

__all__ = [
    "ExtentError",
    "PyramidLevel",
    "VoxelPyramid",
    "build_pyramid",
    "compute_cells",
    "grid_origin",
    "pack_keys",
]


@dataclass(frozen=True, slots=True)
class PyramidLevel:
    """One level of the pyramid: its occupied voxels sorted by key.

    Attributes:
        voxel_size_m: edge length of the voxels.
        cells: ``(n_voxels, 3)`` int64 integer voxel coordinates relative to the origin.
        keys: ``(n_voxels,)`` int64 packed cells, strictly increasing.
        xyz: ``(n_voxels, 3)`` float64 representative points, relative to the origin.
        attributes: ``(n_voxels, n_attributes)`` float64 mean attributes (colour, intensity).
        parent: ``(n_voxels,)`` int64 index of the containing voxel in the next level, -1 at
            the top level.
    """

    voxel_size_m: float
    cells: NDArray[np.int64]
    keys: NDArray[np.int64]
    xyz: NDArray[np.float64]
    attributes: NDArray[np.float64]
    parent: NDArray[np.int64]

    @property
    def n_voxels(self) -> int:
        """Number of occupied voxels."""
        return int(self.keys.shape[0])


@dataclass(frozen=True, slots=True)
class VoxelPyramid:
    """A voxel pyramid and the level-0 voxel of every input point.

    Attributes:
        origin: ``(3,)`` float64 anchor of every grid (absolute coordinates, metres).
        levels: finest first.
        point_voxel: ``(n_points,)`` int64 index of each input point's level-0 voxel.
    """

    origin: NDArray[np.float64]
    levels: tuple[PyramidLevel, ...]
    point_voxel: NDArray[np.int64]

    @property
    def nbytes(self) -> int:
        """Bytes held by the pyramid's arrays."""
        total = self.origin.nbytes + self.point_voxel.nbytes
        for level in self.levels:
            total += sum(
                array.nbytes
                for array in (level.cells, level.keys, level.xyz, level.attributes, level.parent)
            )
        return total

    def ancestors(self, level: int) -> NDArray[np.int64]:
        """For every level-0 voxel, the index of the voxel containing it at ``level``."""
        index = np.arange(self.levels[0].n_voxels, dtype=np.int64)
        for lower in self.levels[:level]:
            index = lower.parent[index]
        return index


def build_pyramid(
    xyz: ArrayLike,
    *,
    base_voxel_size_m: float,
    n_levels: int,
    origin: ArrayLike,
    attributes: ArrayLike | None = None,
) -> VoxelPyramid:
    """Build the voxel pyramid of ``xyz`` (absolute float64 coordinates).

    Args:
        xyz: ``(n, 3)`` points.
        base_voxel_size_m: voxel size of level 0.
        n_levels: number of levels (voxel size doubles per level).
        origin: grid anchor from :func:`grid_origin` (shared by all tiles of a scan).
        attributes: optional ``(n, a)`` values averaged per voxel like the coordinates.
    """
    points = np.ascontiguousarray(xyz, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ShapeError(f"xyz: expected an (n, 3) array, found shape {points.shape}")
    anchor = np.asarray(origin, dtype=np.float64).reshape(3)
    n = points.shape[0]
    values = (
        np.empty((n, 0), np.float64)
        if attributes is None
        else np.ascontiguousarray(attributes, dtype=np.float64).reshape(n, -1)
    )
    if values.shape[0] != n:
        raise ShapeError(f"attributes: expected {n} rows, found {values.shape[0]}")

    cells = compute_cells(points, origin=anchor, voxel_size_m=base_voxel_size_m)
    keys = pack_keys(cells)
    order = np.argsort(keys, kind="stable")
    sorted_keys = keys[order]
    starts = _group_starts(sorted_keys)
    point_voxel = np.empty(n, np.int64)
    point_voxel[order] = np.repeat(np.arange(starts.size - 1), np.diff(starts))
    level_xyz = _group_means(points - anchor, order, starts)
    level_values = _group_means(values, order, starts)
    level_cells = cells[order[starts[:-1]]]
    level_keys = sorted_keys[starts[:-1]]

    levels: list[PyramidLevel] = []
    size = base_voxel_size_m
    for level in range(n_levels):
        if level == n_levels - 1:
            parent = np.full(level_keys.size, -1, np.int64)
            levels.append(
                PyramidLevel(size, level_cells, level_keys, level_xyz, level_values, parent)
            )
            break
        parent_cells = level_cells >> 1
        parent_keys = pack_keys(parent_cells)
        order = np.argsort(parent_keys, kind="stable")
        sorted_parent_keys = parent_keys[order]
        starts = _group_starts(sorted_parent_keys)
        parent = np.empty(level_keys.size, np.int64)
        parent[order] = np.repeat(np.arange(starts.size - 1), np.diff(starts))
        levels.append(PyramidLevel(size, level_cells, level_keys, level_xyz, level_values, parent))
        level_xyz = _group_means(level_xyz, order, starts)
        level_values = _group_means(level_values, order, starts)
        level_cells = parent_cells[order[starts[:-1]]]
        level_keys = sorted_parent_keys[starts[:-1]]
        size *= 2.0
    return VoxelPyramid(origin=anchor, levels=tuple(levels), point_voxel=point_voxel)


def _group_starts(sorted_keys: NDArray[np.int64]) -> NDArray[np.int64]:
    """Start offsets of the runs of equal keys, with the total length appended."""
    if sorted_keys.size == 0:
        return np.zeros(1, np.int64)
    change = np.flatnonzero(sorted_keys[1:] != sorted_keys[:-1]) + 1
    return np.concatenate(([0], change, [sorted_keys.size])).astype(np.int64)


def _group_means(
    values: NDArray[np.float64], order: NDArray[np.int64], starts: NDArray[np.int64]
) -> NDArray[np.float64]:
    """Mean of ``values[order]`` over each run ``starts[i]:starts[i+1]``, summed in order."""
    return _group_means_kernel(np.ascontiguousarray(values), order, starts)


# Hand-written: numpy's reductions sum pairwise or by strided blocks whose order depends on
# the array layout; one sequential loop per group fixes the order (bitwise equal tiles).
@numba.njit(cache=True, nogil=True)
def _group_means_kernel(
    values: NDArray[np.float64], order: NDArray[np.int64], starts: NDArray[np.int64]
) -> NDArray[np.float64]:  # pragma: no cover - compiled
    n_groups = starts.size - 1
    n_columns = values.shape[1]
    out = np.empty((n_groups, n_columns), np.float64)
    for group in range(n_groups):
        begin = starts[group]
        end = starts[group + 1]
        for column in range(n_columns):
            total = 0.0
            for i in range(begin, end):
                total += values[order[i], column]
            out[group, column] = total / (end - begin)
    return out
