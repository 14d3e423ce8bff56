"""Saving and loading a trained :class:`CovarianceModel`.

The file is one JSON header line followed by a joblib payload. The header (format,
package and scikit-learn versions, resolved configuration, feature names, training scans,
seed) is read and checked *before* anything is unpickled, so a model from another
semantic3d or scikit-learn version fails with a clear message instead of a confusing
unpickling error or silently different trees. The payload is a pickle: load only model
files you trust.
"""

from __future__ import annotations

import dataclasses
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from semantic3d.baselines.common.modelfile import ModelFileError, ModelFileFormat
from semantic3d.baselines.covariance.config import config_to_dict
from semantic3d.baselines.covariance.forest import CompiledClassifier
from semantic3d.baselines.covariance.model import CovarianceModel
from semantic3d.core.errors import installed_version, require

FORMAT = "semantic3d-covariance-model"
FORMAT_VERSION = 1
_FILE = ModelFileFormat(
    magic=b"S3DCOV1 ", kind="covariance model", name=FORMAT, version=FORMAT_VERSION
)
_RETRAIN = "semantic3d baseline covariance train"

__all__ = [
    "FORMAT",
    "FORMAT_VERSION",
    "ModelFileError",
    "load_model",
    "read_model_header",
    "save_model",
]


def save_model(model: CovarianceModel, path: str | Path) -> Path:
    """Write ``model`` to ``path`` (parent folders created); returns the path.

    The file is written under a temporary name and renamed when complete: an error or
    Ctrl-C leaves what was at ``path`` as it was.
    """
    joblib: Any = require("joblib", "ml")
    header = {
        "package_version": model.package_version,
        "sklearn_version": installed_version("scikit-learn", "ml"),
        "created": datetime.now(UTC).isoformat(timespec="seconds"),
        "config": config_to_dict(model.config),
        "feature_names": list(model.feature_names),
        "training_scans": list(model.training_scans),
        "n_training_points": {str(k): v for k, v in model.n_training_points.items()},
        "label_values": list(model.label_values),
        "seed": model.seed,
        "training_time_s": model.training_time_s,
        "grid_search": None if model.grid_search is None else model.grid_search.to_dict(),
    }
    # the compiled trees only: loading the file to predict then imports no scikit-learn
    classifier = model.classifier
    compact = classifier if isinstance(classifier, CompiledClassifier) else classifier.compact()
    stored = dataclasses.replace(model, classifier=compact)
    return _FILE.write(path, header, lambda stream: joblib.dump(stored, stream, compress=3))


def read_model_header(path: str | Path) -> dict[str, Any]:
    """The JSON header of a model file, without loading the model."""
    return _FILE.read_header(path)


def load_model(path: str | Path) -> CovarianceModel:
    """Load a model saved by :func:`save_model` with this semantic3d and scikit-learn.

    Raises:
        ModelFileError: not a model file, or written by another package or scikit-learn
            version (retrain it with this version).
    """
    return _FILE.load_joblib(path, payload_type=CovarianceModel, extra="ml", retrain=_RETRAIN)
