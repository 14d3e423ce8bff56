"""What every baseline shares: the prediction loop and its protocol, run records, scans, outputs.

- :mod:`~semantic3d.baselines.common.prediction`: the :class:`Predictor` protocol a trained
  model implements and the streaming loop (:func:`predict_scan`, :func:`predict_scans`).
- :mod:`~semantic3d.baselines.common.run`: the run record (T, points/s, hardware).
- :mod:`~semantic3d.baselines.common.labelbuffer`: labels in any order, read in scan order.
- :mod:`~semantic3d.baselines.common.scans`: labelled scans of any format for training.
- :mod:`~semantic3d.baselines.common.submission`: which scans a run labels and where its files go.
- :mod:`~semantic3d.baselines.common.modelfile`: the model-file header and its version check.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from semantic3d.core.lazy import lazy_exports

if TYPE_CHECKING:
    from semantic3d.baselines.common.labelbuffer import LabelBuffer
    from semantic3d.baselines.common.modelfile import ModelFileError, read_header, write_model_file
    from semantic3d.baselines.common.prediction import (
        LabelledBlock,
        Predictor,
        predict_scan,
        predict_scans,
    )
    from semantic3d.baselines.common.run import (
        HardwareInfo,
        PredictionRun,
        PredictionRunSet,
        describe_hardware,
    )
    from semantic3d.baselines.common.scans import (
        LabelledScan,
        TrainingDataError,
        find_labelled_scans,
    )
    from semantic3d.baselines.common.submission import ScanToLabel, find_scans_to_label

_EXPORTS = {
    "LabelBuffer": "labelbuffer",
    "ModelFileError": "modelfile",
    "read_header": "modelfile",
    "write_model_file": "modelfile",
    "LabelledBlock": "prediction",
    "Predictor": "prediction",
    "predict_scan": "prediction",
    "predict_scans": "prediction",
    "HardwareInfo": "run",
    "PredictionRun": "run",
    "PredictionRunSet": "run",
    "describe_hardware": "run",
    "LabelledScan": "scans",
    "TrainingDataError": "scans",
    "find_labelled_scans": "scans",
    "ScanToLabel": "submission",
    "find_scans_to_label": "submission",
}

__all__ = [
    "HardwareInfo",
    "LabelBuffer",
    "LabelledBlock",
    "LabelledScan",
    "ModelFileError",
    "PredictionRun",
    "PredictionRunSet",
    "Predictor",
    "ScanToLabel",
    "TrainingDataError",
    "describe_hardware",
    "find_labelled_scans",
    "find_scans_to_label",
    "predict_scan",
    "predict_scans",
    "read_header",
    "write_model_file",
]

__getattr__, __dir__ = lazy_exports(
    __name__, {name: f"semantic3d.baselines.common.{module}" for name, module in _EXPORTS.items()}
)
