"""The cubes of one training round: ``rotate_every`` class-balanced batches, one rotation.

A round draws its ``rotate_every x batch_size`` points (every batch class-balanced: the
classes take turns over its slots, each slot a point of its class drawn uniformly over
all scans) and one angle about z, all from ``numpy.random.default_rng((seed, round))``.
Each tile holding drawn points is read with a halo, rotated about its centre, cropped to
the neighbourhood of its drawn points, voxelised, and its drawn points' cubes are filled
and kept bit-packed (2.5 kB a point at the paper's size).

The crop keeps every point within ``(C/2 + 2)`` coarsest voxels of a drawn point on each
axis (a grid of that edge, whole cells next to a drawn point's). A cube reads only the
cells of its block, which lie within ``C/2 + 1`` voxels of its point, and a cell's
summary depends on its own points only: the cubes are those of the whole tile (tested),
while a large scan's tiles with a few drawn points each cost a few blocks, not a tile.

Tiles are prepared side by side on threads (reading, rotating, cropping and the compiled
kernels release the GIL), each on one thread. On a CPU they also fill the cubes; on
a CUDA device the caller's thread fills them there (:mod:`.point_cubes_torch`,
:mod:`.cubes_torch`) and packs them on the device, so a round never crosses the bus.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from semantic3d.baselines.cnn.config import CnnConfig
from semantic3d.baselines.cnn.cubes import Occupancy, build_occupancy, compute_cubes
from semantic3d.core.errors import require
from semantic3d.core.threads import map_in_threads
from semantic3d.spatial.grid import TileKey
from semantic3d.spatial.store import TileStore
from semantic3d.spatial.voxels import CELL_BITS, CELL_OFFSET, MAX_CELL, pack_keys

torch: Any = require("torch", "torch")

__all__ = [
    "Round",
    "RoundCancelledError",
    "RoundProgress",
    "TiledScan",
    "draw_round",
    "make_round",
]


@dataclass(slots=True)
class TiledScan:
    """A training scan in a tile store, with its points per tile and label value."""

    name: str
    store: TileStore
    tiles: tuple[TileKey, ...]
    counts: NDArray[np.int64]  # (n_tiles, N_CLASSES + 1)


@dataclass(frozen=True, slots=True)
class Round:
    """One round's cubes and targets, on the training device.

    Attributes:
        index: the round's number.
        packed: ``(n, ceil(n_scales * C^3 / 8))`` uint8 bit-packed cubes, batch order.
        targets: ``(n,)`` int64 class indices (label value - 1).
    """

    index: int
    packed: Any
    targets: Any


@dataclass(slots=True)
class RoundProgress:
    """Points of the round being made whose cubes are done (shared with the thread that
    makes them; read for the progress bar)."""

    round_index: int = -1
    points: int = 0
    total: int = 0
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def start(self, round_index: int, total: int) -> None:
        with self._lock:
            self.round_index, self.points, self.total = round_index, 0, total

    def add(self, points: int) -> None:
        with self._lock:
            self.points += points


@dataclass(frozen=True, slots=True)
class _Draw:
    slot_classes: NDArray[np.int64]  # label value of each slot
    tile_of: NDArray[np.int64]  # flat tile of each slot (over all scans' tiles)
    ordinal: NDArray[np.int64]  # rank of the slot's point among its tile's points of its class
    angle: float


def draw_round(
    scans: Sequence[TiledScan],
    classes: list[int],
    config: CnnConfig,
    round_index: int,
    n_batches: int,
) -> _Draw:
    """The round's points and angle, from ``default_rng((seed, round_index))``."""
    training = config.training
    rng = np.random.default_rng((training.seed, round_index))
    n_points = n_batches * training.batch_size
    slot_classes = np.concatenate(
        [
            rng.permutation(np.resize(np.asarray(classes), training.batch_size))
            for _ in range(n_batches)
        ]
    )
    angle = float(rng.uniform(0.0, 2.0 * math.pi))
    per_tile = np.concatenate([scan.counts for scan in scans])  # (n_all_tiles, 9)
    tile_of = np.empty(n_points, np.int64)
    ordinal = np.empty(n_points, np.int64)
    for value in classes:
        slots = np.flatnonzero(slot_classes == value)
        cumulative = np.cumsum(per_tile[:, value])
        picks = rng.integers(0, int(cumulative[-1]), slots.size)
        tile_of[slots] = np.searchsorted(cumulative, picks, side="right")
        ordinal[slots] = picks - (cumulative[tile_of[slots]] - per_tile[tile_of[slots], value])
    return _Draw(slot_classes, tile_of, ordinal, angle)


def make_round(
    scans: Sequence[TiledScan],
    classes: list[int],
    config: CnnConfig,
    round_index: int,
    n_batches: int,
    *,
    device: Any,
    n_threads: int = 1,
    progress: RoundProgress | None = None,
    crop: bool = True,
    cancel: threading.Event | None = None,
    device_cubes: bool | None = None,
) -> Round:
    """The cubes and targets of round ``round_index`` (``n_batches`` batches) on ``device``.

    Args:
        scans: the training scans.
        classes: label values trained on.
        config: the configuration.
        round_index: the round's number (seeds its draw).
        n_batches: batches in the round.
        device: the training device.
        n_threads: threads preparing tiles side by side, each running the compiled kernels
            on one thread (1: this thread, with numba's threads).
        progress: counts the points whose cubes are done.
        crop: crop tiles to the drawn points' neighbourhoods (same cubes; off for tests).
        cancel: when set, the round is abandoned between tiles (:class:`RoundCancelledError`).
        device_cubes: fill the cubes with the torch kernels on ``device`` (default: on a
            CUDA device only; the compiled kernels elsewhere).
    """
    device = torch.device(device)
    draw = draw_round(scans, classes, config, round_index, n_batches)
    cubes = config.cubes
    n_points = draw.slot_classes.size
    n_bytes = (cubes.n_scales * cubes.cube_voxels**3 + 7) // 8
    if progress is not None:
        progress.start(round_index, n_points)
    where = [(s, row) for s, scan in enumerate(scans) for row in range(len(scan.tiles))]
    on_device = device.type == "cuda" if device_cubes is None else device_cubes
    flat_tiles = np.unique(draw.tile_of).tolist()

    def prepare(flat_tile: int) -> tuple[NDArray[np.int64], Any]:
        _check(cancel)
        scan_number, row = where[flat_tile]
        slots = np.flatnonzero(draw.tile_of == flat_tile)
        chosen, occupancy = _prepare_tile(scans[scan_number], row, slots, draw, config, crop)
        if on_device:
            return slots, (chosen, occupancy)
        filled = compute_cubes(
            occupancy, chosen, cube_voxels=cubes.cube_voxels, centring=cubes.centring
        )
        packed = np.packbits(filled.reshape(slots.size, -1).astype(np.uint8), axis=1)
        if progress is not None:
            progress.add(slots.size)
        return slots, packed

    prepared: Iterator[tuple[NDArray[np.int64], Any]]
    if n_threads > 1:
        # a tile is small work: tiles side by side, each kernel on one thread (pools of
        # tiles each starting numba's threads on every core oversubscribed a 16-core
        # machine: 28-45 CPU-s for a round that takes 1.7 on one thread)
        prepared = map_in_threads(
            prepare, flat_tiles, n_threads=n_threads, numba_threads_per_task=1, name="round"
        )
    else:
        prepared = map(prepare, flat_tiles)
    targets = torch.as_tensor(draw.slot_classes - 1, dtype=torch.int64)
    if not on_device:
        packed_host = np.zeros((n_points, n_bytes), np.uint8)
        for slots, packed in prepared:
            packed_host[slots] = packed
        return Round(round_index, torch.from_numpy(packed_host), targets)
    from semantic3d.baselines.cnn.point_cubes_torch import pack_cubes

    packed_device = torch.zeros((n_points, n_bytes), dtype=torch.uint8, device=device)
    if cubes.centring == "point":  # the round's tiles side by side: one fill on the device
        tiles = list(prepared)
        _check(cancel)
        anchors, widths = _bands([tile for _, tile in tiles], config)
        for group in _merged_groups(len(tiles), max(widths)):
            slots = np.concatenate([tiles[i][0] for i in group])
            filled = _merged_point_cubes(
                [tiles[i][1] for i in group], [anchors[i] for i in group], widths, config, device
            )
            packed_device[torch.as_tensor(slots, device=device)] = pack_cubes(filled)
            if progress is not None:
                progress.add(slots.size)
        return Round(round_index, packed_device, targets.to(device, non_blocking=True))
    for slots, (chosen, occupancy) in prepared:
        _check(cancel)
        filled = _device_cubes(occupancy, chosen, config, device)
        packed_device[torch.as_tensor(slots, device=device)] = pack_cubes(filled)
        if progress is not None:
            progress.add(slots.size)
    return Round(round_index, packed_device, targets.to(device, non_blocking=True))


class RoundCancelledError(Exception):
    """A round abandoned on request (the run stops)."""


def _check(cancel: threading.Event | None) -> None:
    if cancel is not None and cancel.is_set():
        raise RoundCancelledError


def _prepare_tile(
    scan: TiledScan,
    row: int,
    slots: NDArray[np.int64],
    draw: _Draw,
    config: CnnConfig,
    crop: bool,
) -> tuple[NDArray[np.float64], Occupancy]:
    """The drawn points of one tile, rotated, and the occupancy of their neighbourhood."""
    cubes = config.cubes
    halo = cubes.reach_m * math.sqrt(2.0)  # the rotated tile needs its reach in any direction
    data = scan.store.read(scan.tiles[row], halo_m=halo)
    core_labels = np.asarray(data.core.cloud.labels)
    chosen = np.empty(slots.size, np.int64)
    for value in np.unique(draw.slot_classes[slots]).tolist():
        of_class = slots[draw.slot_classes[slots] == value]
        chosen[np.searchsorted(slots, of_class)] = np.flatnonzero(core_labels == value)[
            draw.ordinal[of_class]
        ]
    x0, y0, x1, y1 = data.bounds
    centre = np.array([(x0 + x1) / 2, (y0 + y1) / 2, 0.0])
    xyz = np.concatenate([np.asarray(data.core.cloud.xyz), np.asarray(data.halo.cloud.xyz)])
    local = xyz - centre
    cos, sin = math.cos(draw.angle), math.sin(draw.angle)
    rotated = np.column_stack(
        [
            cos * local[:, 0] - sin * local[:, 1],
            sin * local[:, 0] + cos * local[:, 1],
            local[:, 2],
        ]
    )
    queries = rotated[chosen]
    if crop:
        reach = (cubes.cube_voxels / 2 + 2) * max(cubes.voxel_sizes_m)
        rotated = rotated[_near(rotated, queries, reach)]
    occupancy = build_occupancy(
        rotated, origin=np.zeros(3), voxel_sizes_m=cubes.voxel_sizes_m, centring=cubes.centring
    )
    return queries, occupancy


def _near(points: NDArray[np.float64], queries: NDArray[np.float64], reach: float) -> Any:
    """A mask of ``points`` holding every point within ``reach`` of a query on each axis
    (and a few more): those in the cells of a grid of edge ``reach`` next to a query's."""
    cells = np.floor(points / reach).astype(np.int64)
    near = np.floor(queries / reach).astype(np.int64)
    steps = np.stack(np.meshgrid(*[np.arange(-1, 2)] * 3, indexing="ij"), -1).reshape(-1, 3)
    around = (np.unique(near, axis=0)[:, None, :] + steps).reshape(-1, 3)
    wanted = np.unique(pack_keys(around))
    keys = pack_keys(cells)
    found = np.minimum(np.searchsorted(wanted, keys), wanted.size - 1)
    return wanted[found] == keys


def _bands(
    tiles: list[tuple[NDArray[np.float64], Occupancy]], config: CnnConfig
) -> tuple[list[tuple[NDArray[np.int64], NDArray[np.float64]]], list[int]]:
    """Per scale, the tiles' points' cells and fractions and the width (cells) of the band
    each tile is moved to along x so that no cube of one tile reaches another's cells:
    twice the largest distance, in cells, of a tile's occupied cells or points from the
    tile's centre, plus a block's reach."""
    from semantic3d.baselines.cnn.point_cubes_torch import compute_anchors

    cubes = config.cubes
    anchors = [
        compute_anchors(chosen, origin=np.zeros(3), voxel_sizes_m=cubes.voxel_sizes_m)
        for chosen, _ in tiles
    ]
    reach = cubes.cube_voxels // 2 + 2
    widths = []
    for scale in range(cubes.n_scales):
        extent = 0
        for (cells, _), (_, occupancy) in zip(anchors, tiles, strict=True):
            summary = occupancy.summaries[scale]  # type: ignore[index]
            if cells.size:
                extent = max(extent, int(np.abs(cells[:, scale, 0]).max()))
            if summary.keys.size:
                x = (summary.keys >> (2 * CELL_BITS)) - CELL_OFFSET
                extent = max(extent, int(np.abs(x).max()))
        widths.append(2 * (extent + reach) + 1)
    return anchors, widths


def _merged_groups(n_tiles: int, widest: int) -> list[list[int]]:
    """The round's ``n_tiles`` tiles in groups whose bands (``widest`` cells at most) keep
    every cell within the packed keys' range (all of a round's tiles at once but for huge
    rounds)."""
    per_group = max(1, (2 * MAX_CELL) // widest - 1)
    return [list(range(i, min(i + per_group, n_tiles))) for i in range(0, n_tiles, per_group)]


def _merged_point_cubes(
    tiles: list[tuple[NDArray[np.float64], Occupancy]],
    anchors: list[tuple[NDArray[np.int64], NDArray[np.float64]]],
    widths: list[int],
    config: CnnConfig,
    device: Any,
) -> Any:
    """Point-centred cubes of several tiles' points in one device fill (``anchors`` and
    band ``widths`` from :func:`_bands`). At every scale tile ``k``'s cells move by ``k``
    bands along x (whole cells: every summary row and point fraction stays as it was) and
    the tiles' summaries are laid end to end, in key order. A cube reads only the cells of
    its block, within its own band: the cubes equal each tile's own, bit for bit."""
    from semantic3d.baselines.cnn.point_cubes import CellSummaries
    from semantic3d.baselines.cnn.point_cubes_torch import DevicePointCubes

    cubes = config.cubes
    first = -(len(tiles) // 2)  # bands centred on cell 0
    merged: list[CellSummaries] = []
    for scale, width in enumerate(widths):
        keys, starts, rows_t, rows, filters = [], [], [], [], []
        n_rows = n_filters = 0
        for k, (_, occupancy) in enumerate(tiles):
            summary = occupancy.summaries[scale]  # type: ignore[index]
            keys.append(summary.keys + (((first + k) * width) << (2 * CELL_BITS)))
            starts.append(summary.starts[:-1] + n_rows)
            rows_t.append(summary.fractions)
            rows.append(np.where(summary.filter_rows < 0, -1, summary.filter_rows + n_filters))
            filters.append(summary.filters)
            n_rows += summary.fractions.shape[0]
            n_filters += summary.filters.shape[0]
        merged.append(
            CellSummaries(
                np.concatenate(keys),
                np.concatenate([*starts, np.array([n_rows], np.int64)]),
                np.concatenate(rows_t),
                np.concatenate(rows).astype(np.int64),
                np.concatenate(filters),
            )
        )
    held = DevicePointCubes(
        Occupancy(np.zeros(3), tuple(cubes.voxel_sizes_m), tuple(m.keys for m in merged),
                  tuple(merged)),
        device=device,
        cube_voxels=cubes.cube_voxels,
    )  # fmt: skip
    cells = np.concatenate([tile_cells for tile_cells, _ in anchors])
    offsets = np.concatenate(
        [np.full(tile_cells.shape[0], first + k) for k, (tile_cells, _) in enumerate(anchors)]
    )
    cells[:, :, 0] += offsets[:, None] * np.asarray(widths)[None, :]
    splits = np.concatenate([tile_splits for _, tile_splits in anchors])
    return held.fill(cells, splits, dtype=torch.uint8)


def _device_cubes(
    occupancy: Occupancy, chosen: NDArray[np.float64], config: CnnConfig, device: Any
) -> Any:
    cubes = config.cubes
    if cubes.centring == "point":
        from semantic3d.baselines.cnn.point_cubes_torch import DevicePointCubes

        held = DevicePointCubes(occupancy, device=device, cube_voxels=cubes.cube_voxels)
        return held.fill_points(chosen, dtype=torch.uint8)
    from semantic3d.baselines.cnn.cubes import compute_corner_cells
    from semantic3d.baselines.cnn.cubes_torch import DeviceOccupancy

    corners = compute_corner_cells(
        chosen,
        origin=occupancy.origin,
        voxel_sizes_m=cubes.voxel_sizes_m,
        cube_voxels=cubes.cube_voxels,
    )
    held_corners = DeviceOccupancy(occupancy, device=device, cube_voxels=cubes.cube_voxels)
    return held_corners.fill(corners, dtype=torch.uint8)
