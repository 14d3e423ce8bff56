"""Integer voxel grids: cells of points relative to an origin, and packed voxel keys.

Every grid of the project (the feature pyramid, tiles, occupancy cubes) is anchored at one
``origin`` and indexes space by integer *cells* ``floor((xyz - origin) / voxel_size_m)``.
Integers, not float bounds, decide which voxel or tile a point falls in, so two passes
over the same points (a tile and the whole scan, two processes) always agree.

A voxel's *key* packs its three cells into one int64 (21 bits each, x then y then z), so
sorting keys orders voxels and equal keys mean the same voxel.

>>> origin = grid_origin([870_000.3, 6_618_000.7, 41.2], coarsest_voxel_size_m=2.56)
>>> np.round(origin, 6).tolist()
[869998.08, 6617999.36, 40.96]
>>> cells = compute_cells(np.array([[870_000.3, 6_618_000.7, 41.2]]), origin=origin, voxel_size_m=0.5)
>>> cells.tolist(), int(pack_keys(cells)[0]) > 0
([[4, 2, 0]], True)
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from semantic3d.core.errors import Semantic3DError

__all__ = [
    "CELL_BITS",
    "CELL_OFFSET",
    "MAX_CELL",
    "ExtentError",
    "compute_cells",
    "grid_origin",
    "pack_keys",
]

CELL_BITS = 21
CELL_OFFSET = 1 << (CELL_BITS - 1)
"""Cells are stored with this offset so that packed keys are non-negative."""

MAX_CELL = CELL_OFFSET - 1
"""Largest absolute cell coordinate (±2**20 voxels from the origin)."""


class ExtentError(Semantic3DError, ValueError):
    """Points lie too far from the grid origin for the packed voxel keys."""


def grid_origin(first_point: ArrayLike, *, coarsest_voxel_size_m: float) -> NDArray[np.float64]:
    """The grid anchor for a scan: ``first_point`` snapped down to the coarsest grid.

    Any fixed point works; a scan-dependent one keeps cells small for georeferenced
    coordinates (x ≈ 870 000). Tiled and whole-scan processing must use the same origin.
    """
    point = np.asarray(first_point, dtype=np.float64).reshape(3)
    if not np.all(np.isfinite(point)):
        raise ExtentError(f"grid origin: expected finite coordinates, found {point.tolist()}")
    return np.floor(point / coarsest_voxel_size_m) * coarsest_voxel_size_m


def compute_cells(
    xyz: NDArray[np.float64], *, origin: NDArray[np.float64], voxel_size_m: float
) -> NDArray[np.int64]:
    """``(n, 3)`` int64 integer voxel coordinates of points relative to ``origin``.

    Raises :class:`ExtentError` when a point lies more than ±2**20 voxels from the origin
    (the range packed keys hold), naming the offending extent.
    """
    cells = np.floor((xyz - origin) / voxel_size_m)
    if cells.size and (cells.min() < -MAX_CELL or cells.max() > MAX_CELL):
        extent = MAX_CELL * voxel_size_m
        raise ExtentError(
            f"points reach {np.abs(xyz - origin).max():.1f} m from the grid origin: expected "
            f"at most {extent:.0f} m (2**20 voxels of {voxel_size_m} m); "
            "use a larger base voxel size or split the scan"
        )
    return cells.astype(np.int64)


def pack_keys(cells: NDArray[np.int64]) -> NDArray[np.int64]:
    """Pack ``(n, 3)`` cells into int64 keys ordered x, then y, then z."""
    shifted = cells + CELL_OFFSET
    return (shifted[:, 0] << (2 * CELL_BITS)) | (shifted[:, 1] << CELL_BITS) | shifted[:, 2]
