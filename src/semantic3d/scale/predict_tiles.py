"""Tiled prediction on a Dask cluster, for any model that labels one tile at a time.

:class:`ClusterTilePredictor` wraps a :class:`~semantic3d.baselines.common.tiles.TiledModel`
(the RandLA-Net baseline's, or any later one) into a
:class:`~semantic3d.baselines.common.prediction.Predictor` whose tiles are labelled by the
workers: the ordinary :func:`~semantic3d.baselines.common.prediction.predict_scan` /
``predict_scans`` loop drives it, so outputs, run records, zips and ``--overwrite`` are
those of the single-process path. This process streams a scan once into a tile store in
the scratch folder (which the workers must see; the same grid and input checks as
:func:`~semantic3d.baselines.common.tiles.iter_tiled_blocks`) and writes the model there
once; each worker opens both once and runs the model's own ``label_tile``. Only tile keys
go out and ``(indices, labels)`` come back: the labels are byte for byte those of one
process, since ``label_tile`` depends on the store and the tile alone.
"""

from __future__ import annotations

import pickle
import shutil
import uuid
from collections.abc import Iterable, Iterator
from functools import lru_cache, partial
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from semantic3d.baselines.common.prediction import LabelledBlock
from semantic3d.baselines.common.tiles import TiledModel, spill_scan
from semantic3d.core.pointcloud import PointCloud
from semantic3d.scale.cluster import DaskCluster, MapProgress
from semantic3d.spatial.grid import TileGrid, TileKey
from semantic3d.spatial.store import TileStore, TileStoreWriter

__all__ = ["ClusterTilePredictor", "label_tile_on_worker"]

MODEL_FILE = "tiled-model-{}.pickle"
"""The model as the workers read it, in the scan's scratch folder."""
STORE_FOLDER = "tiled-store-{}"
"""The scan's tile store, in the scratch folder. Both names carry a fresh token per scan:
workers keep the last opened store and model by path."""


class ClusterTilePredictor:
    """A tiled model whose tiles are labelled by the workers of ``cluster``.

    Args:
        model: the trained model (on the device the workers should use).
        cluster: where the tiles go.
        tile_progress: called with tiles done and total of the scan being labelled.
    """

    def __init__(
        self, model: TiledModel, cluster: DaskCluster, *, tile_progress: MapProgress | None = None
    ) -> None:
        self.model = model
        self.cluster = cluster
        self.tile_progress = tile_progress

    @property
    def training_scans(self) -> tuple[str, ...]:
        return self.model.training_scans

    @property
    def chunk_size(self) -> int:
        return self.model.chunk_size

    def iter_labelled_blocks(
        self, chunks: Iterable[PointCloud], *, workdir: Path
    ) -> Iterator[LabelledBlock]:
        """Tile the scan here, label its tiles on the cluster (blocks in completion order)."""
        workdir.mkdir(parents=True, exist_ok=True)
        token = uuid.uuid4().hex
        model_path = workdir / MODEL_FILE.format(token)
        store_path = workdir / STORE_FOLDER.format(token)

        def writer_of(grid: TileGrid) -> TileStoreWriter:
            # always on disk (never the in-memory store of small scans): workers read it
            return TileStoreWriter(store_path, grid=grid, overwrite=True)

        try:
            store = spill_scan(self.model, chunks, writer_of)
            with model_path.open("wb") as file:
                pickle.dump(self.model, file, protocol=pickle.HIGHEST_PROTOCOL)
            tiled = len(store.tiles) > 1
            task = partial(label_tile_on_worker, str(store_path), str(model_path))
            tiles = sorted(store.tiles, key=lambda tile: (-store.count(tile), tile))
            for _, (indices, labels) in self.cluster.map_unordered(
                task, tiles, progress=self.tile_progress
            ):
                yield LabelledBlock(indices, labels, store.n_points, tiled=tiled)
        finally:
            shutil.rmtree(store_path, ignore_errors=True)
            model_path.unlink(missing_ok=True)


def label_tile_on_worker(
    store_path: str, model_path: str, tile: TileKey
) -> tuple[NDArray[np.int64], NDArray[np.uint8]]:
    """Scan indices and label values of one tile, computed where the scratch folder is
    visible (the model's own ``label_tile``, as in the single-process path)."""
    model = _load_model(model_path)
    indices, labels = model.label_tile(_open_store(store_path), tile)
    return np.asarray(indices, np.int64), np.asarray(labels, np.uint8)


@lru_cache(maxsize=2)
def _load_model(path: str) -> Any:
    # A file this package's client wrote for this job, in a scratch folder it owns.
    with Path(path).open("rb") as file:
        return pickle.load(file)


@lru_cache(maxsize=2)
def _open_store(path: str) -> TileStore:
    return TileStore(path)
