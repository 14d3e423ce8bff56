"""Model files: round trip, header, another version and foreign files rejected."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from semantic3d import __version__
from semantic3d.baselines.covariance.estimator import CovarianceClassifier
from semantic3d.baselines.covariance.forest import CompiledClassifier
from semantic3d.baselines.covariance.model import CovarianceModel
from semantic3d.baselines.covariance.persistence import (
    ModelFileError,
    load_model,
    read_model_header,
    save_model,
)
from semantic3d.baselines.covariance.training import (
    build_training_set,
    find_labelled_scans,
    fit_model,
)
from semantic3d.core.errors import ShapeError
from tests.baselines.conftest import SMALL_CONFIG


@pytest.fixture(scope="module")
def model(scene_dir: Path) -> CovarianceModel:
    scans = find_labelled_scans(scene_dir, names=["train_a"])
    return fit_model(build_training_set(scans, config=SMALL_CONFIG), config=SMALL_CONFIG)


def test_a_saved_model_loads_with_the_same_predictions(
    model: CovarianceModel, tmp_path: Path
) -> None:
    path = save_model(model, tmp_path / "deep" / "model.s3d")
    loaded = load_model(path)
    assert loaded.config == model.config
    assert loaded.feature_names == model.feature_names
    assert loaded.training_scans == ("train_a",)
    assert loaded.seed == 0 and loaded.package_version == __version__
    rows = np.random.default_rng(0).normal(size=(50, len(model.feature_names))).astype(np.float32)
    np.testing.assert_array_equal(loaded.predict_rows(rows), model.predict_rows(rows))
    header = read_model_header(path)
    assert header["feature_names"] == list(model.feature_names)
    assert header["config"]["forest"]["n_estimators"] == 20
    assert header["label_values"] == [1, 2, 3, 4, 5, 6, 8]


def test_a_saved_model_holds_only_the_compiled_trees(
    model: CovarianceModel, tmp_path: Path
) -> None:
    path = save_model(model, tmp_path / "model.s3d")
    loaded = load_model(path)
    assert isinstance(loaded.classifier, CompiledClassifier)
    rows = np.random.default_rng(1).normal(size=(40, len(model.feature_names))).astype(np.float32)
    np.testing.assert_array_equal(
        loaded.classifier.predict_proba(rows), model.classifier.predict_proba(rows)
    )
    np.testing.assert_array_equal(loaded.classifier.predict(rows), model.classifier.predict(rows))
    estimator = model.classifier
    assert isinstance(estimator, CovarianceClassifier)
    np.testing.assert_array_equal(
        loaded.classifier.feature_importances_, estimator.forest_.feature_importances_
    )
    assert loaded.classifier.params == estimator.get_params()
    with pytest.raises(ShapeError, match="finite values, found NaN or infinite values"):
        loaded.classifier.predict_proba(np.full((2, len(model.feature_names)), np.nan))
    # a loaded model saves and loads again as it is
    again = load_model(save_model(loaded, tmp_path / "again.s3d"))
    np.testing.assert_array_equal(again.predict_rows(rows), model.predict_rows(rows))
    # loading it to predict imports no scikit-learn (~0.9 s of every predict's start)
    code = (
        "import sys; from semantic3d.baselines.covariance.persistence import load_model; "
        f"m = load_model({str(path)!r}); "
        "print('sklearn' in sys.modules, type(m.classifier).__name__)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "CompiledClassifier"]


def test_a_model_from_another_version_is_refused(model: CovarianceModel, tmp_path: Path) -> None:
    path = save_model(model, tmp_path / "model.s3d")
    raw = path.read_bytes()
    head, payload = raw.split(b"\n", 1)
    header = json.loads(head[8:])
    header["package_version"] = "0.0.1"
    path.write_bytes(head[:8] + json.dumps(header).encode() + b"\n" + payload)
    with pytest.raises(ModelFileError, match=r"written by semantic3d 0.0.1 .* retrain it"):
        load_model(path)


def test_a_foreign_file_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "model.s3d"
    path.write_bytes(b"PK\x03\x04 not a model")
    with pytest.raises(ModelFileError, match="not a semantic3d covariance model"):
        load_model(path)
    with pytest.raises(ModelFileError, match="cannot read the model"):
        load_model(tmp_path / "absent.s3d")
