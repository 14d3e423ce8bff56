"""``semantic3d baseline cnn train | predict``: a tiny run end to end, refusals, short runs,
Ctrl-C and --resume."""

from __future__ import annotations

import signal
import threading
from pathlib import Path
from typing import Any

import pytest
import torch
from typer.testing import CliRunner

from semantic3d.baselines.cnn.persistence import load_model
from semantic3d.cli import baseline_cnn
from semantic3d.cli.app import app
from semantic3d.io.labels import read_labels
from tests.baselines.cnn.conftest import TINY_TOML, TrainingRun

runner = CliRunner()


def test_train_then_predict_a_scan(cnn_scans: Path, tmp_path: Path) -> None:
    config = tmp_path / "tiny.toml"
    config.write_text(TINY_TOML)
    model = tmp_path / "model.cnn"
    train = ["baseline", "cnn", "train", "--data", str(cnn_scans), "--scans", "train"]
    train += ["--config", str(config), "--out", str(model), "--batches", "2"]
    result = runner.invoke(app, train)
    assert result.exit_code == 0, result.output
    assert "a short run: 2 batches of the configuration's 30" in result.output
    assert "2 batches of 16 (a short run)" in result.output and "parameters" in result.output
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


def test_short_runs_say_so_and_ctrl_c_checkpoints_a_run_that_resume_finishes(
    cnn_scans: Path, tmp_path: Path, training_run: TrainingRun, monkeypatch: pytest.MonkeyPatch
) -> None:
    if threading.current_thread() is not threading.main_thread():
        pytest.skip("signals reach the main thread only")
    config = tmp_path / "tiny.toml"
    config.write_text(TINY_TOML.replace("cube_voxels = 8", 'cube_voxels = 8\ncentring = "corner"'))
    model = tmp_path / "model.cnn"
    train = ["baseline", "cnn", "train", "--data", str(cnn_scans), "--scans", "train"]
    train += ["--config", str(config), "--out", str(model)]
    bar = baseline_cnn._training_bar

    def interrupting(*args: Any) -> Any:
        update = bar(*args)

        def report(state: Any) -> None:
            update(state)
            if state.batch == 5:
                signal.raise_signal(signal.SIGINT)  # Ctrl-C

        return report

    monkeypatch.setattr(baseline_cnn, "_training_bar", interrupting)
    result = runner.invoke(app, train)
    assert result.exit_code == 130, result.output
    assert "interrupted after 5 batches" in result.output and "--resume" in result.output
    assert not model.exists() and (tmp_path / "model.cnn.checkpoint").is_file()
    monkeypatch.setattr(baseline_cnn, "_training_bar", bar)
    result = runner.invoke(app, [*train, "--resume"])
    assert result.exit_code == 0, result.output
    assert "short run" not in result.output
    resumed = load_model(model)  # the model of the run that was not interrupted
    for key, value in training_run.model.network.state_dict().items():
        assert torch.equal(resumed.network.state_dict()[key], value)
    assert not (tmp_path / "model.cnn.checkpoint").exists()
