"""Prediction with the covariance baseline: one cloud in memory, a scan, or many scans.

Scans go through the shared streaming loop (:mod:`semantic3d.baselines.common.prediction`):
any format ``io`` reads, labels written in the input's point order in bounded memory, a
run record (T, hardware) beside them, nothing existing replaced unless asked. The model
itself labels the streamed scan (:meth:`CovarianceModel.iter_labelled_blocks`).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from semantic3d.baselines.common import prediction as _loop
from semantic3d.baselines.common.prediction import Progress, RunProgress
from semantic3d.baselines.common.run import (
    HardwareInfo,
    PredictionRun,
    PredictionRunSet,
    describe_hardware,
)
from semantic3d.baselines.common.submission import ScanToLabel
from semantic3d.baselines.covariance.model import CovarianceModel
from semantic3d.core.pointcloud import PointCloud
from semantic3d.features.multiscale import compute_multiscale_features

__all__ = [
    "HardwareInfo",
    "PredictionRun",
    "PredictionRunSet",
    "Progress",
    "RunProgress",
    "describe_hardware",
    "predict_cloud",
    "predict_scan",
    "predict_scans",
]


def predict_cloud(model: CovarianceModel, cloud: PointCloud) -> NDArray[np.uint8]:
    """Label values of every point of an in-memory cloud."""
    table = compute_multiscale_features(cloud, config=model.config.features)
    return model.predict_rows(table.values)[table.point_row]


def predict_scan(
    model: CovarianceModel,
    points_path: str | Path,
    *,
    out_path: str | Path,
    workdir: str | Path | None = None,
    progress: Progress | None = None,
    overwrite: bool = False,
) -> PredictionRun:
    """Label every point of a scan; write ``.labels`` and a ``.labels.json`` run record.

    See :func:`semantic3d.baselines.common.prediction.predict_scan`.
    """
    return _loop.predict_scan(
        model,
        points_path,
        out_path=out_path,
        workdir=workdir,
        progress=progress,
        overwrite=overwrite,
    )


def predict_scans(
    model: CovarianceModel,
    scans: Sequence[ScanToLabel],
    out: str | Path,
    *,
    workdir: str | Path | None = None,
    progress: RunProgress | None = None,
    overwrite: bool = False,
) -> PredictionRunSet:
    """Label ``scans`` into a folder, or a zip archive when ``out`` ends in ``.zip``.

    See :func:`semantic3d.baselines.common.prediction.predict_scans`.
    """
    return _loop.predict_scans(
        model, scans, out, workdir=workdir, progress=progress, overwrite=overwrite
    )
