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

from semantic3d.core.errors import Semantic3DError, ShapeError

__all__ = [
    "CELL_BITS",
    "CELL_OFFSET",
    "MAX_CELL",
    "ExtentError",
    "compute_cells",
    "grid_origin",
    "group_order",
    "key_order",
    "key_runs",
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
    """``(n, 3)`` int64 integer voxel coordinates of points relative to ``origin``
    (``floor((xyz - origin) / voxel_size_m)``, on every thread).

    Raises :class:`ExtentError` when a point lies more than ±2**20 voxels from the origin
    (the range packed keys hold), or has a coordinate that is not a number, naming the
    offending extent.
    """
    from semantic3d.spatial._kernels import cell_coordinates

    points = np.ascontiguousarray(xyz, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ShapeError(f"xyz: expected (n, 3) coordinates, found {points.shape}")
    anchor = np.ascontiguousarray(origin, dtype=np.float64).reshape(3)
    cells, outside = cell_coordinates(points, anchor, float(voxel_size_m), float(MAX_CELL))
    if outside:
        extent = MAX_CELL * voxel_size_m
        raise ExtentError(
            f"points reach {np.abs(points - anchor).max():.1f} m from the grid origin: expected "
            f"at most {extent:.0f} m (2**20 voxels of {voxel_size_m} m) and finite "
            "coordinates; use a larger base voxel size or split the scan"
        )
    result: NDArray[np.int64] = cells
    return result


def pack_keys(cells: NDArray[np.int64]) -> NDArray[np.int64]:
    """Pack ``(n, 3)`` cells into int64 keys ordered x, then y, then z."""
    from semantic3d.spatial._kernels import packed_keys

    cells = np.ascontiguousarray(cells, dtype=np.int64)
    if cells.ndim != 2 or cells.shape[1] != 3:
        raise ShapeError(f"cells: expected (n, 3) cells, found {cells.shape}")
    keys: NDArray[np.int64] = packed_keys(cells, CELL_OFFSET, CELL_BITS)
    return keys


def key_order(keys: NDArray[np.int64], *, bits: int = CELL_BITS) -> NDArray[np.int64]:
    """The order that sorts packed keys, equal keys in their order: what
    ``np.argsort(keys, kind="stable")`` gives, on every thread of the budget (a radix sort
    of the bits the keys span; hand-written because numpy sorts on one thread, and
    building a scan's voxel pyramid is mostly this sort).

    Keys are three non-negative parts of ``bits`` bits each, the first in the highest
    bits (:func:`packed_keys`; any non-negative key whose first part is below
    ``2**(63 - 2 * bits)``, e.g. ``(ix << bits) | iy``, is sorted as a number)."""
    import numba

    from semantic3d.spatial._kernels import key_order as radix_order

    order: NDArray[np.int64] = radix_order(
        np.ascontiguousarray(keys, dtype=np.int64), int(bits), numba.get_num_threads()
    )
    return order


def group_order(
    groups: NDArray[np.int64], n_groups: int
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
    """Elements grouped by an id ``0..n_groups-1``: ``np.argsort(groups, kind="stable")``,
    each group's bounds in that order (``n_groups + 1``) and every element's place within
    its group. A counting sort on every thread of the budget (the same order whatever the
    threads)."""
    import numba

    from semantic3d.spatial._kernels import group_order as counting_order

    order, bounds, local = counting_order(
        np.ascontiguousarray(groups, dtype=np.int64), int(n_groups), numba.get_num_threads()
    )
    return order, bounds, local


def key_runs(keys: NDArray[np.int64], order: NDArray[np.int64]) -> NDArray[np.int64]:
    """Where each run of equal keys starts in ``keys[order]`` (``order`` from
    :func:`key_order`), with ``len(keys)`` appended: run ``i`` is
    ``order[starts[i]:starts[i + 1]]``."""
    from semantic3d.spatial._kernels import run_starts

    starts: NDArray[np.int64] = run_starts(
        np.ascontiguousarray(keys, dtype=np.int64), np.ascontiguousarray(order, dtype=np.int64)
    )
    return starts
