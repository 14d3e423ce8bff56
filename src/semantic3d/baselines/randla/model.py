"""``RandlaModel``: a trained RandLA-Net with what is needed to label scans, tile by tile.

:meth:`RandlaModel.iter_labelled_blocks` is the
:class:`~semantic3d.baselines.common.Predictor` protocol, through the shared tiled loop
(:func:`~semantic3d.baselines.common.tiles.iter_tiled_blocks`): the streamed scan is
spilled once into a temporary tile store whose tiles are whole voxels, and
:meth:`RandlaModel.label_tile` labels one tile: it reads the tile with a halo of
``[blocks] halo_m``, reduces the points to voxels, cuts the tile into pieces of at most
``max_points`` voxels (:func:`~semantic3d.baselines.randla.blocks.split_tile`), runs one
network pass per piece and gives every point of the tile its voxel's label. Every point
of the scan is labelled exactly once, by the tile it lies in; memory is bounded by a tile,
its halo and one pass, whatever the scan's size.

The random sampling inside the network draws from ``(prediction seed, tile, piece)``, so
the labels are a function of the scan, the model and the seed: the same in every run, in
this process or on a Dask worker (:mod:`semantic3d.scale.predict_tiles` calls the same
:meth:`label_tile`).

On a GPU the neighbour searches run in torch on the device and the network under
bfloat16 autocast (``[prediction] half``), compiled with ``torch.compile`` when
``[prediction] compile`` is set. Tiles are then prepared on ``[prediction]
parallel_tiles`` host threads (reading, voxels, pieces, the points' labels) while the
device runs one pass at a time, so the host work of several tiles overlaps the passes.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import tempfile
import threading
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from semantic3d.baselines.common.device import cpu_threads, resolve_device
from semantic3d.baselines.common.prediction import LabelledBlock, ScanInputError
from semantic3d.baselines.common.tiles import ScanInputs, iter_tiled_blocks
from semantic3d.baselines.randla.blocks import (
    Piece,
    VoxelCloud,
    local_coordinates,
    split_tile,
    turned_about_z,
)
from semantic3d.baselines.randla.config import RandlaConfig
from semantic3d.baselines.randla.levels import build_levels, stack_levels
from semantic3d.baselines.randla.tile_voxels import core_point_labels, read_tile_voxels
from semantic3d.core.errors import require
from semantic3d.core.pointcloud import PointCloud
from semantic3d.spatial.grid import TileGrid, TileKey
from semantic3d.spatial.store import TileStore
from semantic3d.spatial.voxels import grid_origin

torch: Any = require("torch", "torch")

__all__ = ["RandlaModel", "piece_seed", "scan_grid"]

logger = logging.getLogger(__name__)

_SEED_MASK = (1 << 32) - 1


def scan_grid(first_point: NDArray[np.float64], config: RandlaConfig) -> TileGrid:
    """The tiles of a scan: whole voxels of ``[blocks] voxel_size_m``, anchored at the scan's
    first point snapped to the tile grid (voxel cells are taken from that anchor in x and
    y and from 0 in z)."""
    blocks = config.blocks
    edge = blocks.cells_per_tile * blocks.voxel_size_m
    origin = grid_origin(first_point, coarsest_voxel_size_m=edge)
    return TileGrid(
        origin_xy=(float(origin[0]), float(origin[1])),
        cell_size_m=blocks.voxel_size_m,
        cells_per_tile=blocks.cells_per_tile,
    )


def grid_anchor(grid: TileGrid) -> NDArray[np.float64]:
    """The voxel grid's origin of a scan whose tiles are ``grid``."""
    return np.array([grid.origin_xy[0], grid.origin_xy[1], 0.0])


def piece_seed(seed: int, tile: TileKey, number: int) -> list[int]:
    """The seed of a piece's random sampling: the prediction seed, the tile and the piece."""
    return [seed, tile[0] & _SEED_MASK, tile[1] & _SEED_MASK, number]


class RandlaModel:
    """A trained RandLA-Net.

    Attributes:
        network: the :class:`~semantic3d.baselines.randla.network.RandlaNet` (eval mode).
        config: the resolved configuration it was trained with.
        label_values: label values it predicts (one output per value, in order).
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
        config: RandlaConfig,
        label_values: tuple[int, ...],
        training_scans: tuple[str, ...],
        seed: int,
        n_batches_trained: int,
        training_time_s: float,
        package_version: str,
    ) -> None:
        self.network = network.eval()
        self.config = config
        self.label_values = tuple(int(v) for v in label_values)
        self._training_scans = tuple(training_scans)
        self.seed = seed
        self.n_batches_trained = n_batches_trained
        self.training_time_s = training_time_s
        self.package_version = package_version
        self.device = torch.device("cpu")
        self._values = np.asarray(self.label_values, np.uint8)
        self._forward: Any = self.network
        self._device_lock = threading.Lock()

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        state["_forward"] = None  # a compiled network does not pickle; rebuilt on load
        del state["_device_lock"]
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._forward = self.network
        self._device_lock = threading.Lock()

    def _one_pass_at_a_time(self) -> contextlib.AbstractContextManager[Any]:
        """Held around a pass: on a GPU the passes of tiles prepared side by side run one
        after another (one pass's memory on the device); on the CPU they run side by side,
        one torch thread each."""
        return self._device_lock if self.device.type != "cpu" else contextlib.nullcontext()

    @property
    def training_scans(self) -> tuple[str, ...]:
        """Names of the scans it was trained on."""
        return self._training_scans

    @property
    def chunk_size(self) -> int:
        """Points per chunk read while predicting."""
        return self.config.prediction.chunk_size

    def to(self, device: str | Any) -> RandlaModel:
        """Run on ``device`` (``"cpu"``, ``"cuda"``); returns self."""
        self.device = resolve_device(str(device))
        self.network.to(self.device)
        self._forward = self.network
        if self.device.type == "cuda" and self.config.prediction.compile:
            self._forward = torch.compile(self.network, dynamic=True)
        return self

    def configure_prediction(self, **changes: Any) -> RandlaModel:
        """Change ``[prediction]`` settings (``votes``, ``seed``, ``parallel_tiles``...);
        returns self. Raises :class:`~semantic3d.core.errors.ConfigError` on a bad value."""
        prediction = dataclasses.replace(self.config.prediction, **changes)
        self.config = dataclasses.replace(self.config, prediction=prediction)
        return self

    # -- the TiledModel protocol -----------------------------------------------------------
    def tile_grid(self, first_point: NDArray[np.float64]) -> TileGrid:
        """The tiles of a scan whose first point is ``first_point`` (see :func:`scan_grid`)."""
        return scan_grid(first_point, self.config)

    def check_inputs(self, inputs: ScanInputs) -> None:
        """Refuse a scan without the intensity or colours the model was trained with."""
        wanted = self.config.inputs
        if wanted.rgb and not inputs.has_rgb:
            raise ScanInputError(
                "the model was trained with colour inputs (r g b): expected colours, found "
                "none (every point black); use a model trained without them"
            )
        if wanted.intensity and not inputs.has_intensity:
            raise ScanInputError(
                "the model was trained with intensity inputs: expected intensities, found "
                "none (every point 0); use a model trained without them"
            )

    def label_tile(
        self, store: TileStore, tile: TileKey
    ) -> tuple[NDArray[np.int64], NDArray[np.uint8]]:
        """Scan indices and label values of every point of ``tile``, its halo read from
        ``store`` (a store whose grid is :meth:`tile_grid`'s)."""
        blocks = self.config.blocks
        origin = grid_anchor(store.grid)
        held = read_tile_voxels(
            store,
            tile,
            halo_m=blocks.halo_m,
            origin=origin,
            voxel_size_m=blocks.voxel_size_m,
            inputs=self.config.inputs,
        )
        voxels = held.voxels
        cells_per_tile = store.grid.cells_per_tile
        x0, y0 = tile[0] * cells_per_tile, tile[1] * cells_per_tile
        pieces = split_tile(
            voxels,
            core=held.core,
            cell_range=(x0, y0, x0 + cells_per_tile, y0 + cells_per_tile),
            origin=origin,
            voxel_size_m=blocks.voxel_size_m,
            halo_m=blocks.halo_m,
            max_points=blocks.max_points,
        )
        voxel_labels = np.zeros(voxels.n_voxels, np.uint8)
        for piece in pieces:
            voxel_labels[piece.labelled] = self._label_piece(voxels, piece, tile)
        return core_point_labels(
            store, tile, held, voxel_labels, origin=origin, voxel_size_m=blocks.voxel_size_m
        )

    def _label_piece(self, voxels: VoxelCloud, piece: Piece, tile: TileKey) -> NDArray[np.uint8]:
        """Label values of ``piece.labelled`` from ``[prediction] votes`` network passes over
        ``piece.block`` (one: its classes; more: their class probabilities averaged)."""
        prediction = self.config.prediction
        xyz = local_coordinates(voxels.xyz[piece.block], piece.centre_xy)  # block order
        inputs = voxels.inputs[piece.block]
        seed = piece_seed(prediction.seed, tile, piece.number)
        if prediction.votes == 1:
            order = np.random.default_rng(seed).permutation(piece.block.size)
            ordered = xyz[order]
            classes = np.empty(piece.block.size, np.int64)
            classes[order] = self.classify(ordered, np.concatenate([ordered, inputs[order]], 1))
        else:
            total = np.zeros((piece.block.size, len(self.label_values)), np.float32)
            for vote in range(prediction.votes):
                # pass v: its own random order, the block turned by v / votes of a turn
                order = np.random.default_rng([*seed, vote] if vote else seed).permutation(
                    piece.block.size
                )
                ordered = turned_about_z(xyz[order], vote / prediction.votes)
                features = np.concatenate([ordered, inputs[order]], axis=1)
                total[order] += self.class_probabilities(ordered, features)
            classes = np.argmax(total, axis=1)
        return self._values[classes[np.searchsorted(piece.block, piece.labelled)]]

    def classify(
        self, xyz: NDArray[np.float32], features: NDArray[np.float32]
    ) -> NDArray[np.int64]:
        """Class indices (into :attr:`label_values`) of a sub-cloud's points, in the given
        (random) order: ``xyz`` local coordinates, ``features`` the network's inputs."""
        result: NDArray[np.int64] = self._pass(xyz, features, probabilities=False)
        return result

    def class_probabilities(
        self, xyz: NDArray[np.float32], features: NDArray[np.float32]
    ) -> NDArray[np.float32]:
        """``(points, classes)`` softmax of a sub-cloud's points, as :meth:`classify`."""
        result: NDArray[np.float32] = self._pass(xyz, features, probabilities=True)
        return result

    def _pass(
        self, xyz: NDArray[np.float32], features: NDArray[np.float32], *, probabilities: bool
    ) -> NDArray[Any]:
        """One network pass: class indices, or class probabilities."""
        network = self.config.network
        with self._one_pass_at_a_time():
            levels = build_levels(
                xyz, k=network.k_neighbours, ratios=network.ratios, device=self.device
            )
            batch = stack_levels([xyz], [levels], device=self.device)
            inputs = torch.from_numpy(np.ascontiguousarray(features, np.float32))
            with torch.inference_mode():
                if self.device.type == "cuda" and self.config.prediction.half:
                    with torch.autocast("cuda", dtype=torch.bfloat16):
                        logits = self._forward(inputs.to(self.device), batch)
                else:
                    logits = self._forward(inputs.to(self.device), batch)
                if probabilities:
                    return np.asarray(torch.softmax(logits.float(), dim=1).cpu().numpy())
                classes = torch.argmax(logits.float(), dim=1)
            return np.asarray(classes.cpu().numpy().astype(np.int64))

    def iter_labelled_blocks(
        self, chunks: Iterable[PointCloud], *, workdir: Path
    ) -> Iterator[LabelledBlock]:
        """Label a streamed scan tile by tile (the ``Predictor`` protocol).

        ``[prediction] parallel_tiles`` tiles are labelled at a time. On the CPU each runs
        on one torch thread: a pass over a block is many small operations, which threads
        of one operation share badly (on two busy cores, 2 threads per operation ran 4-10x
        slower than 1), while whole tiles side by side keep every core busy. On a GPU the
        tiles' host work runs side by side and their passes one at a time.
        """
        parallel = self.config.prediction.parallel_tiles or cpu_threads()
        if parallel <= 1:
            yield from iter_tiled_blocks(self, chunks, workdir=workdir)
            return
        if self.device.type != "cpu":
            yield from iter_tiled_blocks(self, chunks, workdir=workdir, parallel_tiles=parallel)
            return
        threads = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            yield from iter_tiled_blocks(self, chunks, workdir=workdir, parallel_tiles=parallel)
        finally:
            torch.set_num_threads(threads)

    def label_cloud(self, cloud: PointCloud, *, workdir: Path | None = None) -> NDArray[np.uint8]:
        """Label values of every point of an in-memory cloud (tiled as any scan is)."""
        out = np.zeros(cloud.n_points, np.uint8)
        with tempfile.TemporaryDirectory(prefix="s3d-randla-", dir=workdir) as scratch:
            for block in self.iter_labelled_blocks([cloud], workdir=Path(scratch)):
                out[block.point_indices] = block.labels
        return out
