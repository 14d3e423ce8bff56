"""Saving and loading a trained :class:`CovarianceModel`.

The file is one JSON header line followed by a joblib payload. The header (format,
package and scikit-learn versions, resolved configuration, feature names, training scans,
seed) is read and checked *before* anything is unpickled, so a model from another
semantic3d or scikit-learn version fails with a clear message instead of a confusing
unpickling error or silently different trees. The payload is a pickle: load only model
files you trust.
"""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from semantic3d import __version__
from semantic3d.baselines.common.modelfile import (
    ModelFileError,
    check_versions,
    read_header,
    write_model_file,
)
from semantic3d.baselines.covariance.config import config_to_dict
from semantic3d.baselines.covariance.model import CovarianceModel
from semantic3d.core.errors import require

FORMAT = "semantic3d-covariance-model"
FORMAT_VERSION = 1
_MAGIC = b"S3DCOV1 "
_KIND = "covariance model"
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
    sklearn: Any = require("sklearn", "ml")
    header = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "package_version": model.package_version,
        "sklearn_version": sklearn.__version__,
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
    return write_model_file(
        path,
        magic=_MAGIC,
        header=header,
        write_payload=lambda stream: joblib.dump(model, stream, compress=3),
    )


def read_model_header(path: str | Path) -> dict[str, Any]:
    """The JSON header of a model file, without loading the model."""
    path = Path(path)
    try:
        with path.open("rb") as stream:
            return _read_header(stream, path)
    except OSError as exc:
        raise ModelFileError(f"{path}: cannot read the model: {exc.strerror}") from exc


def load_model(path: str | Path) -> CovarianceModel:
    """Load a model saved by :func:`save_model` with this semantic3d and scikit-learn.

    Raises:
        ModelFileError: not a model file, or written by another package or scikit-learn
            version (retrain it with this version).
    """
    joblib: Any = require("joblib", "ml")
    sklearn: Any = require("sklearn", "ml")
    path = Path(path)
    try:
        with path.open("rb") as stream:
            header = _read_header(stream, path)
            check_versions(
                header,
                path,
                expected={
                    "package_version": ("semantic3d", __version__),
                    "sklearn_version": ("scikit-learn", sklearn.__version__),
                },
                retrain=_RETRAIN,
            )
            model = joblib.load(stream)
    except OSError as exc:
        raise ModelFileError(f"{path}: cannot read the model: {exc.strerror}") from exc
    if not isinstance(model, CovarianceModel):
        raise ModelFileError(
            f"{path}: expected a CovarianceModel payload, found {type(model).__name__}"
        )
    return model


def _read_header(stream: Any, path: Path) -> dict[str, Any]:
    return read_header(
        stream, path, magic=_MAGIC, kind=_KIND, file_format=FORMAT, version=FORMAT_VERSION
    )
