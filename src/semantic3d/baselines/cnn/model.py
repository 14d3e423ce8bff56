"""``CnnModel``: a trained DeepNet with what is needed to label scans, tile by tile.

:meth:`CnnModel.iter_labelled_blocks` is the :class:`~semantic3d.baselines.common.Predictor`
protocol: the streamed scan is spilled once into a temporary tile store
(:mod:`semantic3d.spatial`), and each tile is read with a halo of the cubes' reach, its
occupied cells built, and its points' cubes generated batch by batch as the network
consumes them. Memory is bounded by a tile and a batch, whatever the scan's size; the
labels are those of the whole scan in memory (tested), because every cell and corner is
computed from float64 coordinates relative to one grid origin for the whole scan.

On a CUDA device the network runs channels-last under bf16 autocast, and the next tile is
read and voxelised on the host while the GPU works on the current one. Corner-centred
cubes are filled on the GPU (:mod:`.cubes_torch`); point-centred ones (the default) by
the compiled CPU kernel of :mod:`.point_cubes`, then sent to the device.
"""

from __future__ import annotations

import concurrent.futures
import logging
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from itertools import chain
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from semantic3d.baselines.cnn.config import CnnConfig
from semantic3d.baselines.cnn.cubes import (
    Occupancy,
    build_occupancy,
    compute_corner_cells,
    compute_cubes,
    fill_cubes,
)
from semantic3d.baselines.common.device import DeviceError, resolve_device
from semantic3d.baselines.common.prediction import LabelledBlock
from semantic3d.core.classes import N_CLASSES
from semantic3d.core.errors import require
from semantic3d.core.pointcloud import PointCloud
from semantic3d.spatial.grid import TileGrid, TileKey
from semantic3d.spatial.store import TemporaryTileStore, TileStore
from semantic3d.spatial.voxels import grid_origin, pack_keys

torch: Any = require("torch", "torch")

__all__ = ["CnnModel", "DeviceError", "resolve_device"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class _PreparedTile:
    indices: NDArray[np.int64]
    xyz: NDArray[np.float64]
    occupancy: Occupancy


class CnnModel:
    """A trained DeepNet.

    Attributes:
        network: the :class:`~semantic3d.baselines.cnn.network.DeepNet` (eval mode).
        config: the resolved configuration it was trained with.
        label_values: label values it was trained on (the only ones it predicts).
        training_scans: names of its training scans.
        seed: the training seed.
        n_batches_trained: mini-batches it was trained on.
        training_time_s: wall time of training.
        package_version: semantic3d version that trained it.
        device: where it runs (:meth:`to` moves it).
    """

    def __init__(
        self,
        network: Any,
        *,
        config: CnnConfig,
        label_values: tuple[int, ...],
        training_scans: tuple[str, ...],
        seed: int,
        n_batches_trained: int,
        training_time_s: float,
        package_version: str,
    ) -> None:
        # Channels-last weights: ~1.6x faster convolutions on CPU (oneDNN), and the layout
        # the GPU's tensor cores want. Inputs stay (n, scales, C, C, C): one scale's slice
        # is then contiguous in either layout.
        self.network = network.eval().to(memory_format=torch.channels_last_3d)
        self.config = config
        self.label_values = tuple(int(v) for v in label_values)
        self._training_scans = tuple(training_scans)
        self.seed = seed
        self.n_batches_trained = n_batches_trained
        self.training_time_s = training_time_s
        self.package_version = package_version
        self.device = torch.device("cpu")
        mask = torch.full((N_CLASSES,), float("-inf"))
        mask[[v - 1 for v in self.label_values]] = 0.0
        self._logit_mask = mask

    @property
    def training_scans(self) -> tuple[str, ...]:
        """Names of the scans it was trained on."""
        return self._training_scans

    @property
    def chunk_size(self) -> int:
        """Points per chunk read while predicting."""
        return self.config.prediction.chunk_size

    def to(self, device: str | Any) -> CnnModel:
        """Run on ``device`` (``"cpu"``, ``"cuda"``); returns self."""
        self.device = resolve_device(str(device))
        self.network.to(self.device, memory_format=torch.channels_last_3d)
        self._logit_mask = self._logit_mask.to(self.device)
        return self

    # -- labelling ------------------------------------------------------------------------
    def classify_cubes(self, cubes: Any) -> NDArray[np.uint8]:
        """Label values of ``(n, n_scales, C, C, C)`` cubes (an array or a tensor)."""
        tensor = torch.as_tensor(cubes, device=self.device)
        if tensor.shape[0] == 0:
            return np.empty(0, np.uint8)
        with torch.inference_mode():
            if self.device.type == "cuda":
                with torch.autocast("cuda", dtype=torch.bfloat16):
                    logits = self.network(tensor)
            else:
                logits = self.network(tensor)
            index = torch.argmax(logits.float() + self._logit_mask, dim=1)
        labels: NDArray[np.uint8] = (index.cpu().numpy() + 1).astype(np.uint8)
        return labels

    def label_points(self, xyz: NDArray[np.float64], occupancy: Occupancy) -> NDArray[np.uint8]:
        """Label values of ``(n, 3)`` float64 points whose neighbourhood ``occupancy`` holds.

        With ``prediction.deduplicate`` points whose cubes are identical are classified
        once: the same corner cell at every scale (corner centring), the same coordinates
        (point centring).
        """
        cubes = self.config.cubes
        if cubes.centring == "point":
            return self._label_point_centred(np.asarray(xyz, dtype=np.float64), occupancy)
        corners = compute_corner_cells(
            xyz,
            origin=occupancy.origin,
            voxel_sizes_m=cubes.voxel_sizes_m,
            cube_voxels=cubes.cube_voxels,
        )
        inverse: NDArray[np.int64] | None = None
        if self.config.prediction.deduplicate and corners.shape[0] > 1:
            keys = np.stack([pack_keys(corners[:, s]) for s in range(corners.shape[1])], axis=1)
            _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
            corners = corners[first]
            inverse = inverse.reshape(-1)
        labels = self._label_corners(corners, occupancy)
        return labels if inverse is None else labels[inverse]

    def _label_point_centred(
        self, xyz: NDArray[np.float64], occupancy: Occupancy
    ) -> NDArray[np.uint8]:
        cubes = self.config.cubes
        inverse: NDArray[np.int64] | None = None
        if self.config.prediction.deduplicate and xyz.shape[0] > 1:
            _, first, inverse = np.unique(xyz, axis=0, return_index=True, return_inverse=True)
            xyz = xyz[np.sort(first)]  # distinct points, in their first order
            rank = np.empty(first.size, np.int64)
            rank[np.argsort(first)] = np.arange(first.size)
            inverse = rank[inverse.reshape(-1)]
        batch = self.config.prediction.batch_size
        size = cubes.cube_voxels
        n = xyz.shape[0]
        out = np.empty(n, np.uint8)
        buffer = np.empty((min(batch, n), cubes.n_scales, size, size, size), np.float32)
        for begin in range(0, n, batch):
            part = xyz[begin : begin + batch]
            filled = compute_cubes(
                occupancy, part, cube_voxels=size, centring="point", out=buffer[: part.shape[0]]
            )
            # On a GPU too: the cubes are filled here and sent (see the module docstring).
            out[begin : begin + part.shape[0]] = self.classify_cubes(torch.from_numpy(filled))
        return out if inverse is None else out[inverse]

    def _label_corners(self, corners: NDArray[np.int64], occupancy: Occupancy) -> NDArray[np.uint8]:
        cubes = self.config.cubes
        batch = self.config.prediction.batch_size
        n = corners.shape[0]
        out = np.empty(n, np.uint8)
        if self.device.type == "cuda":
            from semantic3d.baselines.cnn.cubes_torch import DeviceOccupancy

            on_device = DeviceOccupancy(
                occupancy, device=self.device, cube_voxels=cubes.cube_voxels
            )
            for begin in range(0, n, batch):
                filled = on_device.fill(corners[begin : begin + batch])
                out[begin : begin + batch] = self.classify_cubes(filled)
            return out
        size = cubes.cube_voxels
        buffer = np.empty((min(batch, n), cubes.n_scales, size, size, size), np.float32)
        for begin in range(0, n, batch):
            part = corners[begin : begin + batch]
            filled = fill_cubes(occupancy, part, cube_voxels=size, out=buffer[: part.shape[0]])
            out[begin : begin + part.shape[0]] = self.classify_cubes(torch.from_numpy(filled))
        return out

    def label_cloud(self, cloud: PointCloud) -> NDArray[np.uint8]:
        """Label values of every point of an in-memory cloud (no tiling)."""
        if cloud.n_points == 0:
            return np.empty(0, np.uint8)
        origin = self.grid_origin(cloud.xyz[0])
        cubes = self.config.cubes
        occupancy = build_occupancy(
            cloud.xyz, origin=origin, voxel_sizes_m=cubes.voxel_sizes_m, centring=cubes.centring
        )
        return self.label_points(np.asarray(cloud.xyz), occupancy)

    def label_tile(
        self, store: TileStore, tile: TileKey, origin: NDArray[np.float64]
    ) -> tuple[NDArray[np.int64], NDArray[np.uint8]]:
        """Scan indices and label values of one tile's points, its halo read from ``store``.

        The unit of work of :meth:`iter_labelled_blocks`, which another process that sees
        the store can do as well (``origin``: the scan's :meth:`grid_origin`).
        """
        prepared = _prepare(store, tile, origin, self, None)
        return prepared.indices, self.label_points(prepared.xyz, prepared.occupancy)

    def grid_origin(self, first_point: NDArray[np.float64]) -> NDArray[np.float64]:
        """The scan's grid anchor: its first point snapped to the coarsest voxel grid."""
        return grid_origin(first_point, coarsest_voxel_size_m=max(self.config.cubes.voxel_sizes_m))

    def iter_labelled_blocks(
        self,
        chunks: Iterable[PointCloud],
        *,
        workdir: Path,
        select: NDArray[np.int64] | None = None,
    ) -> Iterator[LabelledBlock]:
        """Label a streamed scan tile by tile (the ``Predictor`` protocol).

        Args:
            chunks: the scan's chunks in file order.
            workdir: scratch folder for the tile store (removed afterwards).
            select: label only these points (sorted indices in the scan; for evaluation
                on a sample). Default every point.
        """
        stream = iter(chunks)
        first = next((c for c in stream if c.n_points), None)
        if first is None:
            return
        origin = self.grid_origin(np.asarray(first.xyz[0]))
        grid = TileGrid.square(self.config.prediction.tile_size_m, origin_xy=(origin[0], origin[1]))
        bare = (PointCloud(c.xyz, c.intensity, c.rgb, None) for c in chain([first], stream))
        with TemporaryTileStore(bare, grid=grid, workdir=workdir / "tiles") as store:
            tiled = len(store.tiles) > 1
            for tile in _prefetched(store, store.tiles, origin, self, select):
                labels = self.label_points(tile.xyz, tile.occupancy)
                yield LabelledBlock(tile.indices, labels, store.n_points, tiled=tiled)


def _prepare(
    store: TileStore,
    tile: TileKey,
    origin: NDArray[np.float64],
    model: CnnModel,
    select: NDArray[np.int64] | None,
) -> _PreparedTile:
    cubes = model.config.cubes
    data = store.read(tile, halo_m=cubes.reach_m)
    core = np.asarray(data.core.cloud.xyz)
    indices = np.asarray(data.core.indices).copy()
    keep = None
    if select is not None:
        keep = np.isin(indices, select, assume_unique=True)
        indices = indices[keep]
    neighbourhood = np.concatenate([core, np.asarray(data.halo.cloud.xyz)])
    occupancy = build_occupancy(
        neighbourhood, origin=origin, voxel_sizes_m=cubes.voxel_sizes_m, centring=cubes.centring
    )
    return _PreparedTile(indices, core if keep is None else core[keep], occupancy)


def _prefetched(
    store: TileStore,
    tiles: tuple[TileKey, ...],
    origin: NDArray[np.float64],
    model: CnnModel,
    select: NDArray[np.int64] | None,
) -> Iterator[_PreparedTile]:
    """The tiles, each read and voxelised while the previous one is being classified."""
    with concurrent.futures.ThreadPoolExecutor(max_workers=1) as pool:
        pending = None
        for tile in tiles:
            future = pool.submit(_prepare, store, tile, origin, model, select)
            if pending is not None:
                yield pending.result()
            pending = future
        if pending is not None:
            yield pending.result()
