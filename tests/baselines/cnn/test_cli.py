"""``semantic3d baseline cnn train | predict``: a tiny run end to end, and refusals."""

from __future__ import annotations

from pathlib import Path

from typer.testing import CliRunner

from semantic3d.cli.app import app
from semantic3d.io.labels import read_labels
from tests.baselines.cnn.conftest import TINY_TOML

runner = CliRunner()


def test_train_then_predict_a_scan(cnn_scans: Path, tmp_path: Path) -> None:
    config = tmp_path / "tiny.toml"
    config.write_text(TINY_TOML)
    model = tmp_path / "model.cnn"
    train = ["baseline", "cnn", "train", "--data", str(cnn_scans), "--scans", "train"]
    train += ["--config", str(config), "--out", str(model), "--batches", "2"]
    result = runner.invoke(app, train)
    assert result.exit_code == 0, result.output
    assert "2 batches of 16" in result.output and "parameters" in result.output
    assert model.is_file() and not (tmp_path / "model.cnn.checkpoint").exists()
    again = runner.invoke(app, train)
    assert again.exit_code == 2 and "already exists" in again.output
    out = tmp_path / "predictions"
    predict = ["baseline", "cnn", "predict", str(cnn_scans / "test.txt"), "--model", str(model)]
    result = runner.invoke(app, [*predict, "--out", str(out)])
    assert result.exit_code == 0, result.output
    labels = read_labels(out / "test.labels")
    assert labels.size == read_labels(cnn_scans / "test.labels").size
    assert set(labels.tolist()) <= {1, 3, 5, 8}
    assert (out / "test.labels.json").is_file()
    refused = runner.invoke(app, [*predict, "--out", str(out)])
    assert refused.exit_code == 2 and "already exists" in refused.output
    no_gpu = runner.invoke(app, [*predict, "--out", str(tmp_path / "x"), "--device", "cuda"])
    assert no_gpu.exit_code == 2 or no_gpu.exit_code == 0  # 0 only where a GPU exists
