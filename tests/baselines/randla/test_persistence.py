"""Model files: the round trip gives the same labels; other versions and kinds are refused."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from semantic3d.baselines.common.modelfile import ModelFileError
from semantic3d.baselines.randla.persistence import load_model, read_model_header, save_model
from tests.baselines.randla.conftest import make_scene


def test_round_trip_keeps_the_model(trained: Any, tmp_path: Path) -> None:
    path = save_model(trained, tmp_path / "model.rla")
    header = read_model_header(path)
    assert header["format"] == "semantic3d-randla-model" and header["format_version"] == 1
    assert header["label_values"] == [1, 3, 5, 8] and header["training_scans"] == ["train"]
    assert header["config"]["network"]["channels"] == [8, 16]
    loaded = load_model(path)
    assert loaded.config == trained.config and loaded.label_values == trained.label_values
    cloud = make_scene(2)
    assert np.array_equal(loaded.label_cloud(cloud), trained.label_cloud(cloud))


def test_other_versions_and_kinds_are_refused(trained: Any, tmp_path: Path) -> None:
    path = save_model(trained, tmp_path / "model.rla")
    magic, rest = path.read_bytes().split(b" ", 1)
    line, payload = rest.split(b"\n", 1)
    header = json.loads(line)
    header["format_version"] = 2
    newer = tmp_path / "newer.rla"
    newer.write_bytes(magic + b" " + json.dumps(header).encode() + b"\n" + payload)
    with pytest.raises(ModelFileError, match="expected format semantic3d-randla-model v1, found"):
        load_model(newer)
    (tmp_path / "other.rla").write_bytes(b"S3DCNN1 {}\n")
    with pytest.raises(ModelFileError, match="not a semantic3d RandLA-Net model"):
        load_model(tmp_path / "other.rla")
    (tmp_path / "cut.rla").write_bytes(path.read_bytes()[:-100])
    with pytest.raises(ModelFileError, match="corrupt model weights"):
        load_model(tmp_path / "cut.rla")
