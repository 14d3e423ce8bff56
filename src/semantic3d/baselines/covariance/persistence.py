"""Saving and loading a trained :class:`CovarianceModel`.

The file is one JSON header line followed by a joblib payload. The header (format,
package and scikit-learn versions, resolved configuration, feature names, training scans,
seed) is read and checked *before* anything is unpickled, so a model from another
semantic3d or scikit-learn version fails with a clear message instead of a confusing
unpickling error or silently different trees. The payload is a pickle: load only model
files you trust.
"""

from __future__ import annotations

import json
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from semantic3d import __version__
from semantic3d.baselines.covariance.config import config_to_dict
from semantic3d.baselines.covariance.model import CovarianceModel
from semantic3d.core.errors import Semantic3DError, require

FORMAT = "semantic3d-covariance-model"
FORMAT_VERSION = 1
_MAGIC = b"S3DCOV1 "


class ModelFileError(Semantic3DError, ValueError):
    """A file is not a covariance model, or was written by an incompatible version."""


def save_model(model: CovarianceModel, path: str | Path) -> Path:
    """Write ``model`` to ``path`` (parent folders created); returns the path."""
    joblib: Any = require("joblib", "ml")
    sklearn: Any = require("sklearn", "ml")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
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
    }
    with path.open("wb") as stream:
        stream.write(_MAGIC + json.dumps(header).encode() + b"\n")
        joblib.dump(model, stream, compress=3)
    return path


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
            found = (header.get("package_version"), header.get("sklearn_version"))
            expected = (__version__, sklearn.__version__)
            if found != expected:
                raise ModelFileError(
                    f"{path}: model written by semantic3d {found[0]} with scikit-learn "
                    f"{found[1]}; this is semantic3d {expected[0]} with scikit-learn "
                    f"{expected[1]}: retrain it (semantic3d baseline covariance train)"
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
    line = stream.readline(1 << 20)
    if not line.startswith(_MAGIC):
        raise ModelFileError(f"{path}: not a semantic3d covariance model (bad magic bytes)")
    try:
        header: dict[str, Any] = json.loads(line[len(_MAGIC) :])
    except ValueError as exc:
        raise ModelFileError(f"{path}: corrupt model header: {exc}") from exc
    if header.get("format") != FORMAT or header.get("format_version") != FORMAT_VERSION:
        raise ModelFileError(
            f"{path}: expected format {FORMAT} v{FORMAT_VERSION}, found "
            f"{header.get('format')} v{header.get('format_version')}"
        )
    return header
