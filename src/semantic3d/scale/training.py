"""Covariance-baseline training with the scans read and the training points described on
a Dask cluster.

:func:`train_covariance_model_on_cluster` is
:func:`~semantic3d.baselines.covariance.training.train_covariance_model` with its two hooks
pointed at the cluster: the scans' labels are counted, and the drawn points found, one
task per scan; each training scan is then streamed once here into a
:class:`~semantic3d.features.tiling.TiledScan` in a scratch folder the workers see, and
the tiles holding drawn points are described on the workers (:class:`ClusterRowsOfScan`)
with the same :meth:`~semantic3d.features.tiling.TiledScan.tile_features` the
single-process path calls. Rows come back per tile and are merged in ascending point
order, as the single-process path orders them, so the training set is the same array for
array and the model fitted on it (here, with the same seed) is the same model.
"""

from __future__ import annotations

import pickle
import shutil
import tempfile
from collections.abc import Sequence
from functools import lru_cache, partial
from pathlib import Path
from typing import TypedDict

import numpy as np
from numpy.typing import NDArray

from semantic3d.baselines.common.scans import LabelledScan
from semantic3d.baselines.covariance.config import CovarianceConfig
from semantic3d.baselines.covariance.model import CovarianceModel
from semantic3d.baselines.covariance.training import (
    ItemMapper,
    Progress,
    RowsOfScan,
    ScanRows,
    TrainingSet,
    build_training_set,
    merge_scan_rows,
    train_covariance_model,
)
from semantic3d.features.tiling import TiledScan
from semantic3d.scale.cluster import DaskCluster, MapProgress
from semantic3d.scale.tiled_scans import densest_first, open_tiled_scan
from semantic3d.spatial.grid import TileKey

__all__ = [
    "ClusterRowsOfScan",
    "build_training_set_on_cluster",
    "tile_training_rows",
    "train_covariance_model_on_cluster",
]

SELECTION_FILE = "select.npy"
"""The drawn points of the scan being described, in its scratch folder."""

TileRows = tuple[NDArray[np.int64], NDArray[np.float32], NDArray[np.uint8] | None]
"""``(point_indices, feature rows, label values)`` of the drawn points of one tile."""


class ClusterRowsOfScan:
    """Describes the drawn points of a scan on the workers of ``cluster``, tile by tile.

    A ``rows_of_scan`` hook of
    :func:`~semantic3d.baselines.covariance.training.build_training_set`.

    Args:
        config: the training configuration (features and tiling).
        cluster: where the tiles go.
        workdir: folder for the scans' scratch folders; the workers must see it (default:
            the system's temporary folder, right only for workers on this machine).
        tile_progress: called with tiles done and total of the scan being described.
    """

    def __init__(
        self,
        config: CovarianceConfig,
        cluster: DaskCluster,
        *,
        workdir: str | Path | None = None,
        tile_progress: MapProgress | None = None,
    ) -> None:
        self.config = config
        self.cluster = cluster
        self.workdir = None if workdir is None else Path(workdir)
        self.tile_progress = tile_progress

    def __call__(self, scan: LabelledScan, select: NDArray[np.int64]) -> ScanRows:
        """Rows of the points ``select`` (sorted, unique) of ``scan``, ascending."""
        if self.workdir is not None:
            self.workdir.mkdir(parents=True, exist_ok=True)
        scratch = Path(tempfile.mkdtemp(prefix="s3d-train-", dir=self.workdir))
        try:
            selection = scratch / SELECTION_FILE
            np.save(selection, np.asarray(select, np.int64))
            with TiledScan(
                scan.iter_points(chunk_size=self.config.prediction.chunk_size),
                config=self.config.features,
                tile_size_m=self.config.prediction.tile_size_m,
                workdir=scratch / "tiles",
                whole_level_points=0,  # every level on the workers (see scale.predict)
            ) as tiled:
                tiled.share()
                state = pickle.dumps(tiled, protocol=pickle.HIGHEST_PROTOCOL)
                task = partial(tile_training_rows, str(tiled.workdir), state, str(selection))
                blocks = [
                    rows
                    for _, rows in self.cluster.map_unordered(
                        task, densest_first(tiled), progress=self.tile_progress
                    )
                    if rows[0].size
                ]
        finally:
            shutil.rmtree(scratch, ignore_errors=True)
        return merge_scan_rows(blocks)


def tile_training_rows(
    scan_folder: str, scan_state: bytes, selection_path: str, tile: TileKey
) -> TileRows:
    """Feature rows and labels of the drawn points of one tile (none: empty arrays).

    Args:
        scan_folder: the :class:`TiledScan`'s scratch folder.
        scan_state: the pickled :class:`TiledScan`.
        selection_path: the ``.npy`` file of the scan's drawn points (sorted, unique).
        tile: the tile to describe.
    """
    opened = open_tiled_scan(scan_folder, scan_state)
    features = opened.tile_features(tile, select=_load_selection(selection_path))
    if features is None:
        return np.empty(0, np.int64), np.empty((0, 0), np.float32), np.empty(0, np.uint8)
    return features.point_indices, features.table.point_values(), features.labels


@lru_cache(maxsize=2)
def _load_selection(path: str) -> NDArray[np.int64]:
    # A file this package's client wrote for this job, in a scratch folder it owns.
    selection: NDArray[np.int64] = np.load(path, allow_pickle=False)
    return selection


def build_training_set_on_cluster(
    scans: Sequence[LabelledScan],
    *,
    config: CovarianceConfig,
    cluster: DaskCluster,
    workdir: str | Path | None = None,
    progress: Progress | None = None,
    tile_progress: MapProgress | None = None,
) -> TrainingSet:
    """:func:`~semantic3d.baselines.covariance.training.build_training_set` on ``cluster``.

    The scans must be visible to the workers at the same paths, and ``workdir`` too.
    """
    hooks = _cluster_hooks(config, cluster, workdir, tile_progress)
    return build_training_set(scans, config=config, progress=progress, **hooks)


def train_covariance_model_on_cluster(
    scans: Sequence[LabelledScan],
    *,
    config: CovarianceConfig,
    cluster: DaskCluster,
    workdir: str | Path | None = None,
    progress: Progress | None = None,
    tile_progress: MapProgress | None = None,
) -> CovarianceModel:
    """:func:`~semantic3d.baselines.covariance.training.train_covariance_model` with the
    training set built on ``cluster`` (the forest, and any grid search, fitted here)."""
    hooks = _cluster_hooks(config, cluster, workdir, tile_progress)
    return train_covariance_model(scans, config=config, progress=progress, **hooks)


class _Hooks(TypedDict):
    map_scans: ItemMapper
    rows_of_scan: RowsOfScan


def _cluster_hooks(
    config: CovarianceConfig,
    cluster: DaskCluster,
    workdir: str | Path | None,
    tile_progress: MapProgress | None,
) -> _Hooks:
    """The training hooks that send the scans' work to ``cluster``."""
    return {
        "map_scans": cluster.map,
        "rows_of_scan": ClusterRowsOfScan(
            config, cluster, workdir=workdir, tile_progress=tile_progress
        ),
    }
