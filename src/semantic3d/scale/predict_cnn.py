"""CNN-baseline prediction with the tiles of each scan labelled on a Dask cluster.

:class:`ClusterCnnPredictor` is a :class:`~semantic3d.baselines.common.prediction.Predictor`
like :class:`~semantic3d.scale.predict.ClusterPredictor`: the ordinary
:func:`~semantic3d.baselines.common.prediction.predict_scan` / ``predict_scans`` loop
drives it, so outputs, run records, zips and ``--overwrite`` are those of the
single-process path. This process streams a scan once into a tile store in the scratch
folder (which the workers must see) and writes the model there once; each worker opens
the store, reads a tile with the halo of the cubes' reach and labels its points with the
same :meth:`~semantic3d.baselines.cnn.model.CnnModel.label_tile` the single-process path
runs. Cubes and the network run on the workers (torch threads set from the worker's
thread count); only tile keys go out and ``(indices, labels)`` come back, and the label
buffer writes ``.labels`` in the input's point order, byte for byte those of one process:
``predict_scans(ClusterCnnPredictor(model, cluster), scans, out, workdir=SHARED)``.
"""

from __future__ import annotations

import pickle
import shutil
import uuid
from collections.abc import Iterable, Iterator
from functools import lru_cache, partial
from itertools import chain
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from semantic3d.baselines.common.prediction import LabelledBlock
from semantic3d.core.pointcloud import PointCloud
from semantic3d.scale.cluster import DaskCluster, MapProgress
from semantic3d.spatial.grid import TileGrid, TileKey
from semantic3d.spatial.store import TileStore, TileStoreWriter

__all__ = ["ClusterCnnPredictor", "label_cnn_tile"]

MODEL_FILE = "cnn-model-{}.pickle"
"""The model as the workers read it, in the scan's scratch folder."""
STORE_FOLDER = "cnn-tiles-{}"
"""The scan's tile store, in the scratch folder. Both names carry a fresh token per scan:
workers keep the last opened store and model by path."""


class ClusterCnnPredictor:
    """A CNN model (:class:`~semantic3d.baselines.cnn.model.CnnModel`) whose tiles are
    labelled by the workers of ``cluster``.

    Args:
        model: the trained model (on the device the workers should use).
        cluster: where the tiles go.
        tile_progress: called with tiles done and total of the scan being labelled.
    """

    def __init__(
        self, model: Any, cluster: DaskCluster, *, tile_progress: MapProgress | None = None
    ) -> None:
        self.model = model
        self.cluster = cluster
        self.tile_progress = tile_progress

    @property
    def training_scans(self) -> tuple[str, ...]:
        scans: tuple[str, ...] = self.model.training_scans
        return scans

    @property
    def chunk_size(self) -> int:
        size: int = self.model.chunk_size
        return size

    def iter_labelled_blocks(
        self, chunks: Iterable[PointCloud], *, workdir: Path
    ) -> Iterator[LabelledBlock]:
        """Tile the scan here, label its tiles on the cluster (blocks in completion order)."""
        stream = iter(chunks)
        first = next((c for c in stream if c.n_points), None)
        if first is None:
            return
        origin = self.model.grid_origin(np.asarray(first.xyz[0]))
        grid = TileGrid.square(
            self.model.config.prediction.tile_size_m, origin_xy=(origin[0], origin[1])
        )
        workdir.mkdir(parents=True, exist_ok=True)
        token = uuid.uuid4().hex
        model_path = workdir / MODEL_FILE.format(token)
        store_path = workdir / STORE_FOLDER.format(token)
        try:
            with model_path.open("wb") as file:
                pickle.dump(self.model, file, protocol=pickle.HIGHEST_PROTOCOL)
            # Always on disk (never the in-memory store of small scans): workers read it.
            with TileStoreWriter(store_path, grid=grid, overwrite=True) as writer:
                for chunk in chain([first], stream):
                    writer.add(PointCloud(chunk.xyz, chunk.intensity, chunk.rgb, None))
                store = writer.close()
            tiled = len(store.tiles) > 1
            task = partial(label_cnn_tile, str(store_path), str(model_path), origin)
            tiles = sorted(store.tiles, key=lambda tile: (-store.count(tile), tile))
            for _, (indices, labels) in self.cluster.map_unordered(
                task, tiles, progress=self.tile_progress
            ):
                yield LabelledBlock(indices, labels, store.n_points, tiled=tiled)
        finally:
            shutil.rmtree(store_path, ignore_errors=True)
            model_path.unlink(missing_ok=True)


def label_cnn_tile(
    store_path: str, model_path: str, origin: NDArray[np.float64], tile: TileKey
) -> tuple[NDArray[np.int64], NDArray[np.uint8]]:
    """Scan indices and label values of one tile, computed where the scratch folder is
    visible (the same :meth:`CnnModel.label_tile` as the single-process path)."""
    model = _load_model(model_path)
    indices, labels = model.label_tile(_open_store(store_path), tile, origin)
    return np.asarray(indices, np.int64), np.asarray(labels, np.uint8)


@lru_cache(maxsize=2)
def _load_model(path: str) -> Any:
    # A file this package's client wrote for this job, in a scratch folder it owns.
    with Path(path).open("rb") as file:
        return pickle.load(file)


@lru_cache(maxsize=2)
def _open_store(path: str) -> TileStore:
    return TileStore(path)
