"""Saving and loading a trained :class:`ImageModel`.

The shared model-file layout (:mod:`semantic3d.baselines.common.modelfile`): magic bytes,
one JSON header line (format, versions, variant, resolved configuration, training scans
and stations, classes), then a joblib payload. The header is checked before anything is
unpickled. The encoder-decoder's weights are kept as numpy arrays, so loading a model of
either variant needs no torch until it predicts. The payload is a pickle: load only model
files you trust.
"""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from semantic3d.baselines.common.modelfile import ModelFileError, ModelFileFormat
from semantic3d.baselines.image.config import config_to_dict
from semantic3d.baselines.image.model import ImageModel
from semantic3d.core.errors import require

FORMAT = "semantic3d-image-model"
FORMAT_VERSION = 1
_FILE = ModelFileFormat(magic=b"S3DIMG1 ", kind="image model", name=FORMAT, version=FORMAT_VERSION)
_RETRAIN = "semantic3d baseline image train"

__all__ = [
    "FORMAT",
    "FORMAT_VERSION",
    "ModelFileError",
    "load_model",
    "read_model_header",
    "save_model",
]


def save_model(model: ImageModel, path: str | Path) -> Path:
    """Write ``model`` to ``path`` atomically (parent folders created); returns the path."""
    joblib: Any = require("joblib", "image")
    sklearn: Any = require("sklearn", "image")
    header = {
        "package_version": model.package_version,
        "sklearn_version": sklearn.__version__,
        "created": datetime.now(UTC).isoformat(timespec="seconds"),
        "variant": model.variant.value,
        "config": config_to_dict(model.config),
        "training_scans": list(model.training_scans),
        "training_stations": [list(s) for s in model.training_stations],
        "label_values": list(model.label_values),
        "seed": model.config.seed,
        "training_time_s": model.training_time_s,
    }
    return _FILE.write(path, header, lambda stream: joblib.dump(model, stream, compress=3))


def read_model_header(path: str | Path) -> dict[str, Any]:
    """The JSON header of a model file, without loading the model."""
    return _FILE.read_header(path)


def load_model(path: str | Path) -> ImageModel:
    """Load a model saved by :func:`save_model` with this semantic3d and scikit-learn.

    Raises:
        ModelFileError: not an image model file, or written by other versions.
    """
    return _FILE.load_joblib(path, payload_type=ImageModel, extra="image", retrain=_RETRAIN)
