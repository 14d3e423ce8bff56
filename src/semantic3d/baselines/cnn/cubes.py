"""Occupancy cubes: the network's input, generated on the fly from a tile's points.

Two centrings (``CubeConfig.centring``): ``"point"`` (the paper's, the default) centres
each cube exactly on its point, see :mod:`.point_cubes`; ``"corner"`` (described here,
what models trained before it existed use) takes the block of the scan's grid around the
grid corner nearest the point. :func:`build_occupancy` and :func:`compute_cubes` serve both.

For each scale (voxel size ``v``) the points of a tile and its halo are cut into the
scan's voxel grid (integer cells ``floor((xyz - origin) / v)``, float64 metres relative to
the scan's grid origin, exactly as :func:`semantic3d.spatial.compute_cells` does), and the
occupied cells are kept as sorted packed keys. A point's cube at that scale is the
``C x C x C`` block of that grid centred on the grid corner nearest the point: its cube
voxel ``(i, j, k)`` is the cell ``round((p - origin) / v) - C/2 + (i, j, k)`` and holds 1
when a point lies in that cell. Every voxel of the cube is thus within half a voxel of
where a cube centred exactly on the point would put it, at every scale independently; two
points get the same cubes only when they round to the same corner at all five scales.

Integers decide everything (cells, keys, corners), so a tile with a halo of
:attr:`~semantic3d.baselines.cnn.config.CubeConfig.reach_m` gives its points the very
cubes the whole scan gives them. A scan's cubes are never held: 5 x 16^3 bytes a point
would be 2 TB for a 400 M-point scan; batches are filled as the network asks for them.

The lookup is hand-written (numba): for each of the ``C x C`` columns of a cube one binary
search in the sorted keys finds the column's first cell, and the occupied cells of the
column follow it in key order (z is the fastest axis of a key). numpy has no batched
"which of these 4096 keys exist" short of ``np.isin`` over every cube voxel, which costs
~20x more (``benchmarks/bench_cnn.py``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numba
import numpy as np
from numpy.typing import NDArray

from semantic3d.baselines.cnn.config import CENTRINGS
from semantic3d.baselines.cnn.point_cubes import (
    CellSummaries,
    build_cell_summaries,
    fill_point_cubes,
)
from semantic3d.core.errors import Semantic3DError, ShapeError
from semantic3d.spatial.voxels import CELL_BITS, CELL_OFFSET, compute_cells, pack_keys

__all__ = [
    "CENTRINGS",
    "CentringError",
    "Occupancy",
    "build_occupancy",
    "compute_corner_cells",
    "compute_cubes",
    "fill_cubes",
]


class CentringError(Semantic3DError, ValueError):
    """A cube centring that is not known, or an occupancy built for another centring."""


@dataclass(frozen=True, slots=True)
class Occupancy:
    """Occupied cells of a set of points at every scale.

    Attributes:
        origin: ``(3,)`` float64 grid anchor (absolute metres), shared by every tile of a scan.
        voxel_sizes_m: voxel edge of each scale.
        keys: per scale, the sorted unique packed keys (:func:`semantic3d.spatial.pack_keys`)
            of the occupied cells.
        summaries: per scale, the cells' orthant summaries that point-centred cubes need
            (:mod:`.point_cubes`); ``None`` when built for corner-centred cubes only.
    """

    origin: NDArray[np.float64]
    voxel_sizes_m: tuple[float, ...]
    keys: tuple[NDArray[np.int64], ...]
    summaries: tuple[CellSummaries, ...] | None = None

    @property
    def n_scales(self) -> int:
        """Number of scales."""
        return len(self.voxel_sizes_m)


def build_occupancy(
    xyz: NDArray[np.float64],
    *,
    origin: NDArray[np.float64],
    voxel_sizes_m: Sequence[float],
    centring: str = "corner",
) -> Occupancy:
    """The occupied cells of ``(n, 3)`` float64 points at each voxel size.

    With ``centring="point"`` each cell also gets the summary point-centred cubes need
    (the keys are the same either way).
    """
    xyz = _as_xyz(xyz, "xyz")
    origin = np.asarray(origin, dtype=np.float64).reshape(3)
    _check_centring(centring)
    if centring == "point":
        summaries = tuple(
            build_cell_summaries(xyz, origin=origin, voxel_size_m=float(v)) for v in voxel_sizes_m
        )
        return Occupancy(
            origin,
            tuple(float(v) for v in voxel_sizes_m),
            tuple(s.keys for s in summaries),
            summaries,
        )
    keys = tuple(
        np.unique(pack_keys(compute_cells(xyz, origin=origin, voxel_size_m=float(v))))
        for v in voxel_sizes_m
    )
    return Occupancy(origin, tuple(float(v) for v in voxel_sizes_m), keys)


def compute_corner_cells(
    xyz: NDArray[np.float64],
    *,
    origin: NDArray[np.float64],
    voxel_sizes_m: Sequence[float],
    cube_voxels: int,
) -> NDArray[np.int64]:
    """``(n, n_scales, 3)`` first cell of each point's cube at each scale.

    ``round((p - origin) / v) - cube_voxels / 2`` (halves round up), computed in float64.
    """
    xyz = _as_xyz(xyz, "xyz")
    origin = np.asarray(origin, dtype=np.float64).reshape(3)
    out = np.empty((xyz.shape[0], len(voxel_sizes_m), 3), np.int64)
    half = cube_voxels // 2
    for scale, size in enumerate(voxel_sizes_m):
        out[:, scale] = np.floor((xyz - origin) / float(size) + 0.5).astype(np.int64) - half
    return out


def fill_cubes(
    occupancy: Occupancy,
    corners: NDArray[np.int64],
    *,
    cube_voxels: int,
    out: NDArray[np.float32] | None = None,
) -> NDArray[np.float32]:
    """``(n, n_scales, C, C, C)`` float32 occupancy (0 or 1) of the cubes at ``corners``.

    Args:
        occupancy: the occupied cells of the tile and its halo.
        corners: ``(n, n_scales, 3)`` from :func:`compute_corner_cells`.
        cube_voxels: ``C``.
        out: an array of that shape to fill (reused between batches), else a new one.

    Axis order of a cube is x, y, z.
    """
    n_scales = occupancy.n_scales
    if corners.ndim != 3 or corners.shape[1:] != (n_scales, 3):
        raise ShapeError(f"corners: expected (n, {n_scales}, 3), found {corners.shape}")
    shape = (corners.shape[0], n_scales, cube_voxels, cube_voxels, cube_voxels)
    if out is None:
        out = np.empty(shape, np.float32)
    elif out.shape != shape or out.dtype != np.float32 or not out.flags.c_contiguous:
        raise ShapeError(f"out: expected a C-contiguous float32 {shape}, found {out.shape}")
    if corners.shape[0] == 0:
        return out
    lengths = np.array([k.shape[0] for k in occupancy.keys], np.int64)
    starts = np.zeros(n_scales + 1, np.int64)
    starts[1:] = np.cumsum(lengths)
    flat = (
        np.concatenate(occupancy.keys) if starts[-1] else np.zeros(1, np.int64)
    )  # one array: numba takes no tuple of arrays of varying length cheaply
    _fill(flat, starts, np.ascontiguousarray(corners, dtype=np.int64), cube_voxels, out)
    return out


def compute_cubes(
    occupancy: Occupancy,
    xyz: NDArray[np.float64],
    *,
    cube_voxels: int,
    centring: str,
    out: NDArray[np.float32] | None = None,
) -> NDArray[np.float32]:
    """``(n, n_scales, C, C, C)`` float32 cubes of ``(n, 3)`` float64 points.

    Args:
        occupancy: the occupied cells of the tile and its halo
            (:func:`build_occupancy` with the same ``centring``).
        xyz: the points whose cubes are wanted.
        cube_voxels: ``C``.
        centring: ``"point"`` or ``"corner"`` (see the module docstring).
        out: an array of that shape to fill (reused between batches), else a new one.
    """
    _check_centring(centring)
    if centring == "corner":
        corners = compute_corner_cells(
            xyz,
            origin=occupancy.origin,
            voxel_sizes_m=occupancy.voxel_sizes_m,
            cube_voxels=cube_voxels,
        )
        return fill_cubes(occupancy, corners, cube_voxels=cube_voxels, out=out)
    if occupancy.summaries is None:
        raise CentringError(
            "occupancy: expected cell summaries for point-centred cubes, found an occupancy "
            'built for corner-centred ones (build_occupancy(..., centring="point"))'
        )
    return fill_point_cubes(
        occupancy.summaries,
        _as_xyz(xyz, "xyz"),
        origin=occupancy.origin,
        voxel_sizes_m=occupancy.voxel_sizes_m,
        cube_voxels=cube_voxels,
        out=out,
    )


def _check_centring(centring: str) -> None:
    if centring not in CENTRINGS:
        raise CentringError(f"centring: expected one of {list(CENTRINGS)}, found {centring!r}")


@numba.njit(cache=True, nogil=True, parallel=True)
def _fill(
    keys: NDArray[np.int64],
    starts: NDArray[np.int64],
    corners: NDArray[np.int64],
    size: int,
    out: NDArray[np.float32],
) -> None:  # pragma: no cover - compiled
    n = corners.shape[0]
    n_scales = corners.shape[1]
    x_shift = 2 * CELL_BITS
    for point in numba.prange(n):
        for scale in range(n_scales):
            cube = out[point, scale]
            cube[:] = 0.0
            lo = starts[scale]
            hi = starts[scale + 1]
            if lo == hi:
                continue
            bx = corners[point, scale, 0] + CELL_OFFSET
            by = corners[point, scale, 1] + CELL_OFFSET
            bz = corners[point, scale, 2] + CELL_OFFSET
            for i in range(size):
                for j in range(size):
                    first = ((bx + i) << x_shift) | ((by + j) << CELL_BITS) | bz
                    last = first + size
                    # lower bound of ``first`` in keys[lo:hi]
                    a = lo
                    b = hi
                    while a < b:
                        m = (a + b) >> 1
                        if keys[m] < first:
                            a = m + 1
                        else:
                            b = m
                    while a < hi and keys[a] < last:
                        cube[i, j, keys[a] - first] = 1.0
                        a += 1


def _as_xyz(xyz: NDArray[np.float64], name: str) -> NDArray[np.float64]:
    array = np.asarray(xyz, dtype=np.float64)
    if array.ndim != 2 or array.shape[1] != 3:
        raise ShapeError(f"{name}: expected (n, 3) coordinates, found {array.shape}")
    return array
