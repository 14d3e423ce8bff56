"""Covariance-baseline prediction with the tiles of each scan labelled on a Dask cluster.

:class:`ClusterPredictor` is a :class:`~semantic3d.baselines.common.prediction.Predictor`:
the ordinary :func:`~semantic3d.baselines.common.prediction.predict_scan` /
``predict_scans`` loop drives it, so outputs, run records, zips and ``--overwrite`` are
those of the single-process path. This process streams a scan once into a
:class:`~semantic3d.features.tiling.TiledScan` (tile store and voxel pyramids in the
scratch folder, which the workers must see) and computes once what every tile shares
(:meth:`~semantic3d.features.tiling.TiledScan.share`); each worker opens the scan from
that folder once, computes one tile's features with the same
:meth:`~semantic3d.features.tiling.TiledScan.tile_features` the single-process path
calls and classifies them with the same ``row_probabilities`` and
``label_probabilities``; the labels come back with the
points' positions and go into the label buffer, which writes ``.labels`` in the input's
point order. Every scan is tiled here, small ones too: tiled rows equal whole-scan rows
bit for bit, so the labels are byte for byte those of the single-process path.
"""

from __future__ import annotations

import pickle
from collections.abc import Iterable, Iterator, Sequence
from functools import lru_cache, partial
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from semantic3d.baselines.common.prediction import (
    LabelledBlock,
    Progress,
    RunProgress,
    predict_scan,
    predict_scans,
)
from semantic3d.baselines.common.run import PredictionRun, PredictionRunSet
from semantic3d.baselines.common.submission import ScanToLabel
from semantic3d.baselines.covariance.context import last_points, row_centroids
from semantic3d.baselines.covariance.model import CovarianceModel, point_cells
from semantic3d.core.pointcloud import PointCloud
from semantic3d.features.tiling import TiledScan
from semantic3d.scale.cluster import DaskCluster, MapProgress
from semantic3d.scale.tiled_scans import densest_first, open_tiled_scan
from semantic3d.spatial.grid import TileKey

__all__ = [
    "ClusterPredictor",
    "TileLabels",
    "label_tile",
    "predict_scan_on_cluster",
    "predict_scans_on_cluster",
]

MODEL_FILE = "model.pickle"
"""The model as the workers read it, in the scan's scratch folder."""

_PART_POINTS = 1 << 21
"""A tile's points read at a time to place its rows."""

TileLabels = tuple[NDArray[np.int64], NDArray[np.uint8]]
"""``(point_indices, label_values)`` of one tile."""


class ClusterPredictor:
    """A covariance model whose tiles are labelled by the workers of ``cluster``.

    Args:
        model: the trained model.
        cluster: where the tiles go.
        tile_progress: called with tiles done and total of the scan being labelled.
    """

    def __init__(
        self,
        model: CovarianceModel,
        cluster: DaskCluster,
        *,
        tile_progress: MapProgress | None = None,
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

    @property
    def max_parallel_scans(self) -> int:
        """One scan at a time: the cluster labels each scan's tiles in parallel."""
        return 1

    def iter_labelled_blocks(
        self, chunks: Iterable[PointCloud], *, workdir: Path
    ) -> Iterator[LabelledBlock]:
        """Tile the scan here, label its tiles on the cluster (blocks in completion order)."""
        prediction = self.model.config.prediction
        model_path = workdir / MODEL_FILE
        with model_path.open("wb") as stream:
            pickle.dump(self.model, stream, protocol=pickle.HIGHEST_PROTOCOL)
        with TiledScan(
            chunks,
            config=self.model.config.features,
            tile_size_m=prediction.tile_size_m,
            workdir=workdir / "tiles",
            # Every level tile by tile, on the workers: describing coarse levels whole is
            # a serial pass here (a third of a scan's feature time) that the workers would
            # wait for; tile by tile costs ~4 % more work in all and gives the same rows.
            whole_level_points=0,
        ) as scan:
            scan.share()  # each level's first halo: computed once, here
            # The scan travels as bytes, opened once per worker process: a task message
            # that arrives after the scan was closed must not touch its removed folder.
            scan_state = pickle.dumps(scan, protocol=pickle.HIGHEST_PROTOCOL)
            task = partial(label_tile, str(scan.workdir), scan_state, str(model_path))
            tiles = densest_first(scan)
            for _, (indices, labels) in self.cluster.map_unordered(
                task, tiles, progress=self.tile_progress
            ):
                yield LabelledBlock(indices, labels, scan.n_points, tiled=True)


def label_tile(scan_folder: str, scan_state: bytes, model_path: str, tile: TileKey) -> TileLabels:
    """Label values of one tile's points, computed where the scan's folder is visible.

    The same features (:meth:`TiledScan.tile_features`, the forest run on the rows as they
    are made: :meth:`CovarianceModel.row_probabilities`) and labelling
    (:meth:`CovarianceModel.label_probabilities`) as the single-process path.

    Args:
        scan_folder: the :class:`TiledScan`'s scratch folder (the key it is kept under).
        scan_state: the pickled :class:`TiledScan` (paths and numbers).
        model_path: the pickled model.
        tile: the tile to label.
    """
    opened = open_tiled_scan(scan_folder, scan_state)
    model = _load_pickled_model(model_path)
    # the forest on the rows as they are made, as in one process: the table is never whole;
    # nor are the tile's points copied (a scan's densest tile grows with the scan)
    features = opened.tile_features(tile, row_map=model.row_probabilities, positions=False)
    if features is None:
        return np.empty(0, np.int64), np.empty(0, np.uint8)
    table = features.table
    assert table.mapped is not None and opened.origin is not None
    row_xyz = None
    if model.needs_row_positions(table):  # per-point rows, or a scan of a few voxels
        # positions relative to the grid origin, as in one process
        xyz = opened.store.read_core(tile).copied().cloud.xyz
        relative = (xyz - opened.origin).astype(np.float32)
        row_xyz = row_centroids(relative, table.point_row, table.n_rows)
    # the squares a dense tile's graph is cut in: a row's is its last point's, as in one
    # process, the tile's points read a part at a time
    last = last_points(table.point_row, table.n_rows)
    row_cell = np.zeros(table.n_rows, np.uint16)
    start = 0
    for part in opened.store.iter_core_parts(tile, _PART_POINTS):
        stop = start + part.n_points
        rows = np.flatnonzero((last >= start) & (last < stop))
        xyz = part.cloud.xyz[last[rows] - start]  # only the rows' last points, gathered
        row_cell[rows] = point_cells(xyz, origin=opened.origin, config=model.config)
        start = stop
    labels = model.label_probabilities(
        table.mapped, row_xyz=row_xyz, row_cell=row_cell, neighbours=table.neighbours
    )[table.point_row]
    return features.point_indices, labels


@lru_cache(maxsize=2)
def _load_pickled_model(path: str) -> CovarianceModel:
    # A file this package's client wrote for this job, in a scratch folder it owns.
    with Path(path).open("rb") as stream:
        model: CovarianceModel = pickle.load(stream)
    return model


def predict_scan_on_cluster(
    model: CovarianceModel,
    points_path: str | Path,
    *,
    cluster: DaskCluster,
    out_path: str | Path,
    workdir: str | Path | None = None,
    progress: Progress | None = None,
    overwrite: bool = False,
) -> PredictionRun:
    """:func:`~semantic3d.baselines.common.prediction.predict_scan` with tiles on ``cluster``.

    ``workdir`` must be a folder the workers see (shared filesystem) unless the cluster
    runs on this machine.
    """
    return predict_scan(
        ClusterPredictor(model, cluster),
        points_path,
        out_path=out_path,
        workdir=workdir,
        progress=progress,
        overwrite=overwrite,
    )


def predict_scans_on_cluster(
    model: CovarianceModel,
    scans: Sequence[ScanToLabel],
    out: str | Path,
    *,
    cluster: DaskCluster,
    workdir: str | Path | None = None,
    progress: RunProgress | None = None,
    overwrite: bool = False,
) -> PredictionRunSet:
    """:func:`~semantic3d.baselines.common.prediction.predict_scans` with tiles on ``cluster``."""
    return predict_scans(
        ClusterPredictor(model, cluster),
        scans,
        out,
        workdir=workdir,
        progress=progress,
        overwrite=overwrite,
    )
