"""Prediction with the covariance baseline: one cloud in memory, a scan, or many scans.

``predict_scan`` and ``predict_scans`` are the shared streaming loop
(:mod:`semantic3d.baselines.common.prediction`), which a :class:`CovarianceModel` drives:
any format ``io`` reads, labels written in the input's point order in bounded memory, a
run record (T, hardware) beside them, nothing existing replaced unless asked. The model
itself labels the streamed scan (:meth:`CovarianceModel.iter_labelled_blocks`).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from semantic3d.baselines.common.prediction import (
    Progress,
    RunProgress,
    predict_scan,
    predict_scans,
)
from semantic3d.baselines.common.run import (
    HardwareInfo,
    PredictionRun,
    PredictionRunSet,
    describe_hardware,
)
from semantic3d.baselines.covariance.context import row_centroids
from semantic3d.baselines.covariance.model import (
    CovarianceModel,
    concurrent_scans_supported,
    point_cells,
    point_tiles,
)
from semantic3d.core.pointcloud import PointCloud
from semantic3d.features.multiscale import compute_multiscale_features
from semantic3d.features.pyramid import grid_origin

__all__ = [
    "HardwareInfo",
    "PredictionRun",
    "PredictionRunSet",
    "Progress",
    "RunProgress",
    "concurrent_scans_supported",
    "describe_hardware",
    "predict_cloud",
    "predict_scan",
    "predict_scans",
]


def predict_cloud(model: CovarianceModel, cloud: PointCloud) -> NDArray[np.uint8]:
    """Label values of every point of an in-memory cloud."""
    table = compute_multiscale_features(cloud, config=model.config.features)
    if not model.context.enabled or cloud.n_points == 0:
        return model.predict_rows(table.values)[table.point_row]
    origin = grid_origin(
        cloud.xyz[0], coarsest_voxel_size_m=model.config.features.coarsest_voxel_size_m
    )
    row_tile = np.zeros(table.n_rows, np.int64)
    row_tile[table.point_row] = point_tiles(cloud.xyz, origin=origin, config=model.config)
    row_cell = np.zeros(table.n_rows, np.uint16)
    row_cell[table.point_row] = point_cells(cloud.xyz, origin=origin, config=model.config)
    row_xyz = None
    if model.needs_row_positions(table):
        relative = (cloud.xyz - origin).astype(np.float32)
        row_xyz = row_centroids(relative, table.point_row, table.n_rows)
    labels = model.predict_rows(
        table.values,
        row_xyz=row_xyz,
        row_tile=row_tile,
        row_cell=row_cell,
        neighbours=table.neighbours,
    )
    return labels[table.point_row]
