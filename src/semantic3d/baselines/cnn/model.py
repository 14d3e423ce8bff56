"""``CnnModel``: a trained DeepNet with what is needed to label scans, tile by tile.

:meth:`CnnModel.iter_labelled_blocks` is the :class:`~semantic3d.baselines.common.Predictor`
protocol: the streamed scan is spilled once into a temporary tile store
(:mod:`semantic3d.spatial`), and each tile is read with a halo of the cubes' reach, its
occupied cells built, and its points' cubes generated batch by batch as the network
consumes them. Memory is bounded by a tile and a batch, whatever the scan's size; the
labels are those of the whole scan in memory (tested), because every cell and corner is
computed from float64 coordinates relative to one grid origin for the whole scan.

Three things overlap: the next tile is read and voxelised in a thread while the current
one is labelled, and inside a tile the next batches' cubes are made by a producer thread
while the network classifies (:mod:`.labelling`). On a CUDA device the cubes are born on
the device (:mod:`.point_cubes_torch`, :mod:`.cubes_torch`) and the network runs in
float16, channels-last, compiled once the work pays for it (:mod:`.inference`).
"""

from __future__ import annotations

import concurrent.futures
import logging
import threading
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from itertools import chain
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from semantic3d.baselines.cnn.config import CnnConfig
from semantic3d.baselines.cnn.cubes import Occupancy, build_occupancy, compute_corner_cells
from semantic3d.baselines.cnn.inference import InferenceNetwork
from semantic3d.baselines.cnn.labelling import label_tile_points
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
        self._inference: InferenceNetwork | None = None
        self._inference_lock = threading.Lock()

    def __getstate__(self) -> dict[str, Any]:
        """Pickled (for Dask workers) without its labelling form, made again there."""
        state = dict(self.__dict__)
        state["_inference"] = None
        del state["_inference_lock"]
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._inference_lock = threading.Lock()

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
        self._inference = None
        return self

    @property
    def inference(self) -> InferenceNetwork:
        """The network's labelling form on :attr:`device` (made once, kept: a compiled
        network is compiled once per process, not per scan)."""
        with self._inference_lock:
            if self._inference is None or self._inference.device != self.device:
                prediction = self.config.prediction
                cuda = self.device.type == "cuda"
                self._inference = InferenceNetwork(
                    self.network,
                    device=self.device,
                    precision=prediction.precision,
                    compile=prediction.compile,
                    batch_size=prediction.device_batch_size if cuda else prediction.batch_size,
                    logit_mask=self._logit_mask,
                )
            return self._inference

    # -- labelling ------------------------------------------------------------------------
    def classify_cubes(self, cubes: Any) -> NDArray[np.uint8]:
        """Label values of ``(n, n_scales, C, C, C)`` cubes (an array or a tensor)."""
        tensor = torch.as_tensor(cubes, device=self.device)
        if tensor.shape[0] == 0:
            return np.empty(0, np.uint8)
        inference = self.inference
        parts = []
        for begin in range(0, tensor.shape[0], inference.batch_size):
            index, _ = inference.classify(
                tensor[begin : begin + inference.batch_size], precise=True
            )
            parts.append(index)
        labels: NDArray[np.uint8] = (torch.cat(parts).cpu().numpy() + 1).astype(np.uint8)
        return labels

    def label_points(self, xyz: NDArray[np.float64], occupancy: Occupancy) -> NDArray[np.uint8]:
        """Label values of ``(n, 3)`` float64 points whose neighbourhood ``occupancy`` holds.

        With ``prediction.deduplicate`` points whose cubes are identical are classified
        once: the same corner cell at every scale (corner centring), the same coordinates
        (point centring).
        """
        xyz = np.asarray(xyz, dtype=np.float64)
        first, inverse = self._distinct(xyz, occupancy)
        distinct = xyz if first is None else xyz[first]
        index = label_tile_points(self.inference, distinct, occupancy, cubes=self.config.cubes)
        labels = (index + 1).astype(np.uint8)
        return labels if inverse is None else labels[inverse]

    def _distinct(
        self, xyz: NDArray[np.float64], occupancy: Occupancy
    ) -> tuple[NDArray[np.int64] | None, NDArray[np.int64] | None]:
        """Rows of the points whose cubes are distinct (in their first order) and each
        point's row among them; ``(None, None)`` when every point is classified."""
        if not self.config.prediction.deduplicate or xyz.shape[0] < 2:
            return None, None
        cubes = self.config.cubes
        if cubes.centring == "point":
            identity = xyz
        else:
            corners = compute_corner_cells(
                xyz,
                origin=occupancy.origin,
                voxel_sizes_m=cubes.voxel_sizes_m,
                cube_voxels=cubes.cube_voxels,
            )
            identity = np.stack([pack_keys(corners[:, s]) for s in range(corners.shape[1])], axis=1)
        _, first, inverse = np.unique(identity, axis=0, return_index=True, return_inverse=True)
        order = np.sort(first)
        rank = np.empty(first.size, np.int64)
        rank[np.argsort(first)] = np.arange(first.size)
        return order, rank[inverse.reshape(-1)]

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
            self.inference.expect(store.n_points if select is None else select.size)
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
