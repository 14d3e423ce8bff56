"""From points to the voxel blocks the network sees: grid reduction, windows and tile pieces.

Points are reduced to one per occupied voxel of the scan's grid (RandLA-Net's grid
sub-sampling): the voxel's barycentre, the mean of its points' inputs and, for training,
the most frequent label among its labelled points. Voxels are integer cells relative to
one origin per scan (:mod:`semantic3d.spatial.voxels`), so a tile and its neighbours
always agree on them, and the tile grid is made of whole voxels: a voxel lies in exactly
one tile. Every point takes its voxel's label back.

A *window* is the set of voxels within a square (any height) about a centre; when it holds
more than ``max_points`` voxels, the ones nearest the centre (Chebyshev distance in xy)
are kept. Training sub-clouds are windows about training points. At prediction a tile's
*pieces* are windows about its core: the core whole, or, when the core and its halo hold
more than ``max_points`` voxels, the core cut into quarters (recursively), each with its
own halo.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from semantic3d.baselines.randla.config import InputConfig
from semantic3d.core.classes import N_CLASSES
from semantic3d.core.pointcloud import PointCloud
from semantic3d.spatial.voxels import compute_cells, pack_keys

__all__ = [
    "Piece",
    "VoxelCloud",
    "local_coordinates",
    "point_inputs",
    "split_tile",
    "turned_about_z",
    "voxelise",
    "window",
]


@dataclass(frozen=True, slots=True)
class VoxelCloud:
    """Points reduced to one per occupied voxel (voxels in key order).

    Attributes:
        xyz: ``(m, 3)`` float64 barycentre of each voxel's points (absolute metres).
        cells: ``(m, 3)`` int64 integer cell of each voxel.
        inputs: ``(m, c)`` float32 mean input channels (intensity, colour) of its points.
        labels: ``(m,)`` uint8 most frequent label value among its labelled points (0 when
            none is labelled), or None without labels.
        inverse: ``(n,)`` int64 voxel of each input point.
    """

    xyz: NDArray[np.float64]
    cells: NDArray[np.int64]
    inputs: NDArray[np.float32]
    labels: NDArray[np.uint8] | None
    inverse: NDArray[np.int64]

    @property
    def n_voxels(self) -> int:
        """Occupied voxels."""
        return int(self.xyz.shape[0])


def point_inputs(cloud: PointCloud, config: InputConfig) -> NDArray[np.float32]:
    """``(n, c)`` float32 input channels of points besides their coordinates: the intensity
    over ``intensity_scale``, then r, g, b over 255 (as the configuration asks)."""
    columns: list[NDArray[np.float32]] = []
    if config.intensity:
        columns.append((np.asarray(cloud.intensity, np.float32) / config.intensity_scale)[:, None])
    if config.rgb:
        columns.append(np.asarray(cloud.rgb, np.float32) / 255.0)
    if not columns:
        return np.empty((cloud.n_points, 0), np.float32)
    return np.ascontiguousarray(np.concatenate(columns, axis=1), dtype=np.float32)


def voxelise(
    xyz: NDArray[np.float64],
    *,
    origin: NDArray[np.float64],
    voxel_size_m: float,
    inputs: NDArray[np.float32],
    labels: NDArray[np.uint8] | None = None,
) -> VoxelCloud:
    """Reduce ``(n, 3)`` float64 points to their occupied voxels (see :class:`VoxelCloud`)."""
    cells = compute_cells(np.asarray(xyz, np.float64), origin=origin, voxel_size_m=voxel_size_m)
    keys = pack_keys(cells)
    unique_keys, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1).astype(np.int64)
    m = unique_keys.size
    counts = np.bincount(inverse, minlength=m).astype(np.float64)
    centres = np.empty((m, 3), np.float64)
    for axis in range(3):
        centres[:, axis] = np.bincount(inverse, weights=xyz[:, axis], minlength=m) / counts
    means = np.empty((m, inputs.shape[1]), np.float32)
    for column in range(inputs.shape[1]):
        means[:, column] = np.bincount(inverse, weights=inputs[:, column], minlength=m) / counts
    voxel_labels = None
    if labels is not None:
        votes = np.bincount(
            inverse * (N_CLASSES + 1) + labels.astype(np.int64), minlength=m * (N_CLASSES + 1)
        ).reshape(m, N_CLASSES + 1)
        votes[:, 0] = 0  # unlabelled points do not vote
        voxel_labels = np.where(votes.any(axis=1), votes.argmax(axis=1), 0).astype(np.uint8)
    return VoxelCloud(centres, cells[first], means, voxel_labels, inverse)


def window(
    xyz: NDArray[np.float64],
    *,
    centre_xy: NDArray[np.float64],
    half_width_m: float,
    max_points: int,
) -> NDArray[np.int64]:
    """Sorted indices of the voxels within ``half_width_m`` of ``centre_xy`` (x and y), the
    ``max_points`` nearest (Chebyshev distance, ties by index) when more."""
    distance = np.max(np.abs(xyz[:, :2] - centre_xy), axis=1)
    inside = np.flatnonzero(distance <= half_width_m)
    if inside.size > max_points:
        nearest = np.argsort(distance[inside], kind="stable")[:max_points]
        inside = np.sort(inside[nearest])
    return inside.astype(np.int64)


@dataclass(frozen=True, slots=True)
class Piece:
    """One network pass of a tile: a block of voxels and which of them it labels.

    Attributes:
        block: sorted indices of the voxels the network sees.
        labelled: indices of the voxels whose labels it keeps (a part of the tile's core).
        centre_xy: the centre of the core part it labels (the block's local origin).
        number: its position among the tile's pieces (seeds its random sampling).
    """

    block: NDArray[np.int64]
    labelled: NDArray[np.int64]
    centre_xy: NDArray[np.float64]
    number: int


def split_tile(
    voxels: VoxelCloud,
    *,
    core: NDArray[np.bool_],
    cell_range: tuple[int, int, int, int],
    origin: NDArray[np.float64],
    voxel_size_m: float,
    halo_m: float,
    max_points: int,
) -> list[Piece]:
    """The pieces of a tile: its core voxels (``core``), each labelled by exactly one piece.

    Args:
        voxels: the tile's and its halo's voxels.
        core: which voxels belong to the tile.
        cell_range: ``(x0, y0, x1, y1)`` the tile's cells, half-open.
        origin: the scan's grid origin.
        voxel_size_m: the grid's voxel edge.
        halo_m: context kept around each piece's core part.
        max_points: voxels of one pass; a core part is quartered while its block holds
            more and it holds more than a quarter of them.
    """
    pieces: list[Piece] = []
    core_ids = np.flatnonzero(core)
    core_cells = voxels.cells[core_ids]

    def visit(x0: int, y0: int, x1: int, y1: int) -> None:
        mine = core_ids[
            (core_cells[:, 0] >= x0)
            & (core_cells[:, 0] < x1)
            & (core_cells[:, 1] >= y0)
            & (core_cells[:, 1] < y1)
        ]
        if mine.size == 0:
            return
        low = origin[:2] + np.array([x0, y0]) * voxel_size_m
        high = origin[:2] + np.array([x1, y1]) * voxel_size_m
        centre = (low + high) / 2
        outside = np.max(
            np.maximum(np.maximum(low - voxels.xyz[:, :2], voxels.xyz[:, :2] - high), 0.0), axis=1
        )
        near = np.flatnonzero(outside <= halo_m)
        wide = x1 - x0 > 1 or y1 - y0 > 1
        if near.size > max_points and mine.size > max_points // 4 and wide:
            mx, my = (x0 + x1 + 1) // 2, (y0 + y1 + 1) // 2
            for box in ((x0, y0, mx, my), (mx, y0, x1, my), (x0, my, mx, y1), (mx, my, x1, y1)):
                if box[0] < box[2] and box[1] < box[3]:
                    visit(*box)
            return
        if near.size > max_points:  # keep the core part and the nearest of its halo
            is_mine = np.zeros(voxels.n_voxels, np.bool_)
            is_mine[mine] = True
            halo = near[~is_mine[near]]
            keep = max(max_points - mine.size, 0)
            nearest = np.argsort(outside[halo], kind="stable")[:keep]
            near = np.sort(np.concatenate([mine, halo[nearest]]))
        pieces.append(Piece(near, mine, centre, len(pieces)))

    visit(*cell_range)
    return pieces


def local_coordinates(
    xyz: NDArray[np.float64], centre_xy: NDArray[np.float64]
) -> NDArray[np.float32]:
    """``(m, 3)`` float32 coordinates about a block's local origin: its centre in x and y,
    the median height of its voxels in z (a block's frame, the same at training and
    prediction; float64 until the subtraction, so georeferenced scans keep millimetres)."""
    if xyz.shape[0] == 0:
        return np.empty((0, 3), np.float32)
    origin = np.array([centre_xy[0], centre_xy[1], float(np.median(xyz[:, 2]))])
    return np.ascontiguousarray(xyz - origin, dtype=np.float32)


def turned_about_z(xyz: NDArray[np.float32], turns: float) -> NDArray[np.float32]:
    """``xyz`` (local coordinates) turned by ``turns`` of a full turn about the z axis.

    >>> turned_about_z(np.array([[1.0, 0.0, 2.0]], np.float32), 0.25).round(6).tolist()
    [[0.0, 1.0, 2.0]]
    """
    if turns == 0:
        return xyz
    angle = 2.0 * np.pi * turns
    cos, sin = np.cos(angle), np.sin(angle)
    out = xyz.copy()
    out[:, 0] = cos * xyz[:, 0] - sin * xyz[:, 1]
    out[:, 1] = sin * xyz[:, 0] + cos * xyz[:, 1]
    return out
