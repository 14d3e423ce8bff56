"""A tile's voxels, read from the tile store strip by strip: memory follows the voxels, not
the points.

Near a terrestrial scanner a tile can hold tens of millions of points that a few million
voxels sum up; reading the tile and its halo whole held ~200 bytes a point at once (the
records, their copy, cells, keys, the sort behind ``np.unique``). Here the tile and its
halo are read in strips of whole voxel columns along x (the keys are ordered x first, so
the strips' voxels laid end to end are in key order), each strip reduced to its voxels
before the next is read. A voxel lies in one strip, and inside a strip its points come in
the order the whole tile's read gives them (each tile's points in the order they were
streamed), so every voxel's sums, and so the voxels, equal :func:`~.blocks.voxelise`'s of
the whole block bit for bit. Strips are narrowed where the tiles are dense, to about
:data:`STRIP_POINTS` points each.

Labels go back to the tile's own points in a second pass of strips over the tile alone:
each point takes its voxel's label (a search in the sorted keys), and only the points'
scan indices and labels are kept (9 bytes a point).

Needs the ``[randla]`` extra (numpy only here).
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from semantic3d.baselines.randla.blocks import VoxelCloud, point_inputs, voxelise
from semantic3d.baselines.randla.config import InputConfig
from semantic3d.core.pointcloud import PointCloud
from semantic3d.spatial.grid import Bounds, TileKey
from semantic3d.spatial.store import TilePoints, TileStore
from semantic3d.spatial.voxels import compute_cells, pack_keys

__all__ = ["STRIP_POINTS", "TileVoxels", "core_point_labels", "read_tile_voxels"]

STRIP_POINTS = 1 << 20
"""Points a strip is cut to hold, about (strips are whole voxel columns)."""


class TileVoxels:
    """A tile's and its halo's voxels (:class:`~.blocks.VoxelCloud` without the points'
    ``inverse``), their keys, and which of them hold points of the tile itself.

    Attributes:
        voxels: the voxels, in key order.
        keys: ``(m,)`` int64 packed keys of their cells (sorted).
        core: ``(m,)`` bool, True for a voxel holding a point of the tile.
    """

    __slots__ = ("core", "keys", "voxels")

    def __init__(self, voxels: VoxelCloud, keys: NDArray[np.int64], core: NDArray[np.bool_]):
        self.voxels = voxels
        self.keys = keys
        self.core = core


def _strips(
    store: TileStore,
    box: Bounds,
    *,
    origin: NDArray[np.float64],
    voxel_size_m: float,
    tiles: list[TileKey],
    strip_points: int,
) -> Iterator[tuple[int, int, Bounds]]:
    """Half-open ranges ``[c0, c1)`` of voxel columns covering ``box`` in x (and a column
    beyond each side: a point on the box's edge may round into it), each holding about
    ``strip_points`` points by the store's sub-cell counts (at least one column), with the
    box to read for each: the strip's columns, a hair wider on the inner sides (float
    rounding of the cells), within ``box``."""
    first = math.floor((box[0] - origin[0]) / voxel_size_m) - 1
    last = math.floor((box[2] - origin[0]) / voxel_size_m) + 1
    per_column = _column_counts(store, box, tiles, origin, voxel_size_m, first, last)
    hair = voxel_size_m * 1e-3
    c0 = first
    while c0 <= last:
        c1, held = c0 + 1, per_column[c0 - first]
        while c1 <= last and held + per_column[c1 - first] <= strip_points:
            held += per_column[c1 - first]
            c1 += 1
        low = box[0] if c0 == first else max(box[0], origin[0] + c0 * voxel_size_m - hair)
        high = box[2] if c1 > last else min(box[2], origin[0] + c1 * voxel_size_m + hair)
        yield c0, c1, (low, box[1], high, box[3])
        c0 = c1


def _column_counts(
    store: TileStore,
    box: Bounds,
    tiles: list[TileKey],
    origin: NDArray[np.float64],
    voxel_size_m: float,
    first: int,
    last: int,
) -> NDArray[np.float64]:
    """Points of ``tiles`` in each voxel column ``first..last`` of ``box``, estimated from
    the sub-cells (a sub-cell's points spread evenly over the columns it spans)."""
    counts = np.zeros(last - first + 1, np.float64)
    n_sub = store.subdivisions
    sub = store.grid.tile_size_m / n_sub
    for tile in tiles:
        t_x0, t_y0, _, _ = store.grid.tile_bounds(tile)
        rows = store.sub_cell_counts(tile)
        y_low = max(0, math.floor((box[1] - t_y0) / sub))
        y_high = min(n_sub - 1, math.floor((box[3] - t_y0) / sub))
        if y_low > y_high:
            continue
        per_x = rows[:, y_low : y_high + 1].sum(axis=1)
        for sx in np.flatnonzero(per_x):
            a = math.floor((t_x0 + sx * sub - origin[0]) / voxel_size_m)
            b = math.floor((t_x0 + (sx + 1) * sub - origin[0]) / voxel_size_m)
            a, b = max(a, first), min(b, last)
            if a <= b:
                counts[a - first : b - first + 1] += per_x[sx] / (b - a + 1)
    return counts


def _grown(box: Bounds, by: float) -> Bounds:
    return (box[0] - by, box[1] - by, box[2] + by, box[3] + by)


def _tile_part(
    store: TileStore,
    tile: TileKey,
    strip: Bounds,
    voxel_size_m: float,
    *,
    core: bool,
    others: list[TileKey] | None = None,
) -> Iterator[tuple[TileKey, TilePoints]]:
    """The points of a strip: the tile's own read a hair wider (every point of the tile
    belongs to it, whatever rounding put it on its edge), or the ``others``' within it."""
    if core:
        yield from store.read_box_parts(_grown(strip, voxel_size_m * 1e-3), tiles=[tile])
    else:
        yield from store.read_box_parts(strip, tiles=others or [])


@dataclass(frozen=True, slots=True)
class _StripVoxels:
    voxels: VoxelCloud
    keys: NDArray[np.int64]
    core: NDArray[np.bool_]


def _reduce(
    xyz: NDArray[np.float64],
    values: NDArray[np.float32],
    mine: NDArray[np.bool_],
    labels: NDArray[np.uint8] | None,
    origin: NDArray[np.float64],
    voxel_size_m: float,
) -> _StripVoxels:
    """A strip's points reduced to voxels by :func:`~.blocks.voxelise`, with their keys and
    which of them hold points of the tile (``mine``)."""
    voxels = voxelise(xyz, origin=origin, voxel_size_m=voxel_size_m, inputs=values, labels=labels)
    core = np.bincount(voxels.inverse, weights=mine, minlength=voxels.n_voxels) > 0
    return _StripVoxels(voxels, pack_keys(voxels.cells), core)


def read_tile_voxels(
    store: TileStore,
    tile: TileKey,
    *,
    halo_m: float,
    origin: NDArray[np.float64],
    voxel_size_m: float,
    inputs: InputConfig,
    labels: bool = False,
    strip_points: int = STRIP_POINTS,
) -> TileVoxels:
    """The voxels of ``tile`` (all its points) and of its halo of ``halo_m`` (the other
    tiles' points within ``halo_m`` of its rectangle, edges included), as
    :meth:`~TileStore.read` reads them; with ``labels``, each voxel's most frequent label
    (the store's labels, as :func:`~.blocks.voxelise` votes)."""
    x_min, y_min, x_max, y_max = store.grid.tile_bounds(tile)
    box = (x_min - halo_m, y_min - halo_m, x_max + halo_m, y_max + halo_m)
    n_inputs = point_inputs(PointCloud.from_arrays(np.zeros((0, 3))), inputs).shape[1]
    strips: list[_StripVoxels] = []
    near = store.tiles_near(box)
    others = [t for t in near if t != tile] if halo_m > 0 else []  # no halo: not even edges
    for c0, c1, strip in _strips(
        store, box, origin=origin, voxel_size_m=voxel_size_m, tiles=near,
        strip_points=strip_points,
    ):  # fmt: skip
        xyz_parts: list[NDArray[np.float64]] = []
        input_parts: list[NDArray[np.float32]] = []
        mine_parts: list[NDArray[np.bool_]] = []
        label_parts: list[NDArray[np.uint8]] = []
        for core in (True, False):  # the tile's own points first, as the whole read
            for _, points in _tile_part(store, tile, strip, voxel_size_m, core=core, others=others):
                xyz = np.asarray(points.cloud.xyz, np.float64)
                columns = np.floor((xyz[:, 0] - origin[0]) / voxel_size_m)
                keep = (columns >= c0) & (columns < c1)
                if keep.any():
                    xyz_parts.append(xyz[keep])
                    input_parts.append(point_inputs(points.cloud[keep], inputs))
                    mine_parts.append(np.full(int(keep.sum()), core))
                    if labels:
                        label_parts.append(np.asarray(points.cloud.labels)[keep])
        if xyz_parts:
            strips.append(
                _reduce(
                    np.concatenate(xyz_parts),
                    np.concatenate(input_parts),
                    np.concatenate(mine_parts),
                    np.concatenate(label_parts) if labels else None,
                    origin,
                    voxel_size_m,
                )
            )
    voxels = VoxelCloud(
        np.concatenate([s.voxels.xyz for s in strips]) if strips else np.empty((0, 3)),
        np.concatenate([s.voxels.cells for s in strips]) if strips else np.empty((0, 3), np.int64),
        np.concatenate([s.voxels.inputs for s in strips])
        if strips
        else np.empty((0, n_inputs), np.float32),
        np.concatenate([s.voxels.labels for s in strips if s.voxels.labels is not None])
        if labels and strips
        else (np.zeros(0, np.uint8) if labels else None),
        np.empty(0, np.int64),  # the points' voxels are found again by core_point_labels
    )
    keys = np.concatenate([s.keys for s in strips]) if strips else np.empty(0, np.int64)
    in_core = np.concatenate([s.core for s in strips]) if strips else np.zeros(0, np.bool_)
    return TileVoxels(voxels, keys, in_core)


def core_point_labels(
    store: TileStore,
    tile: TileKey,
    voxels: TileVoxels,
    voxel_labels: NDArray[np.uint8],
    *,
    origin: NDArray[np.float64],
    voxel_size_m: float,
    strip_points: int = STRIP_POINTS,
) -> tuple[NDArray[np.int64], NDArray[np.uint8]]:
    """Scan indices and labels of every point of ``tile``: its voxel's label."""
    indices: list[NDArray[np.int64]] = []
    labels: list[NDArray[np.uint8]] = []
    box = store.grid.tile_bounds(tile)
    for c0, c1, strip in _strips(
        store, box, origin=origin, voxel_size_m=voxel_size_m, tiles=[tile],
        strip_points=strip_points,
    ):  # fmt: skip
        for _, points in _tile_part(store, tile, strip, voxel_size_m, core=True):
            xyz = np.asarray(points.cloud.xyz, np.float64)
            columns = np.floor((xyz[:, 0] - origin[0]) / voxel_size_m)
            keep = np.flatnonzero((columns >= c0) & (columns < c1))
            if keep.size == 0:
                continue
            keys = pack_keys(compute_cells(xyz[keep], origin=origin, voxel_size_m=voxel_size_m))
            labels.append(voxel_labels[np.searchsorted(voxels.keys, keys)])
            indices.append(np.asarray(points.indices, np.int64)[keep])
    if not indices:
        return np.empty(0, np.int64), np.empty(0, np.uint8)
    return np.concatenate(indices), np.concatenate(labels)
