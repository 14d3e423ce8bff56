"""``semantic3d baseline randla train | predict | cv``: a tiny run end to end, and refusals."""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

from typer.testing import CliRunner

from semantic3d.cli.app import app
from semantic3d.io.labels import read_labels
from tests.baselines.randla.conftest import TINY_TOML

runner = CliRunner()


def test_train_predict_and_cross_validate(randla_scans: Path, tmp_path: Path) -> None:
    config = tmp_path / "tiny.toml"
    config.write_text(TINY_TOML)
    model = tmp_path / "model.rla"
    train = ["baseline", "randla", "train", "--data", str(randla_scans), "--scans", "train"]
    train += ["--config", str(config), "--out", str(model), "--batches", "2"]
    result = runner.invoke(app, train)
    assert result.exit_code == 0, result.output
    assert "2 batches of 2 sub-clouds" in result.output and "parameters" in result.output
    assert model.is_file() and not (tmp_path / "model.rla.checkpoint").exists()
    again = runner.invoke(app, train)
    assert again.exit_code == 2 and "already exists" in again.output
    both = runner.invoke(app, [*train[:-2], "--overwrite", "--preset", "paper"])
    assert both.exit_code == 2 and "expected --config or --preset, found both" in both.output

    out = tmp_path / "predictions"
    predict = [
        "baseline",
        "randla",
        "predict",
        str(randla_scans / "test.txt"),
        "--model",
        str(model),
    ]
    result = runner.invoke(app, [*predict, "--out", str(out)])
    assert result.exit_code == 0, result.output
    labels = read_labels(out / "test.labels")
    assert labels.size == read_labels(randla_scans / "test.labels").size
    assert set(labels.tolist()) <= {1, 3, 5, 8} and (out / "test.labels.json").is_file()
    refused = runner.invoke(app, [*predict, "--out", str(out)])
    assert refused.exit_code == 2 and "already exists" in refused.output
    voted = runner.invoke(app, [*predict, "--out", str(tmp_path / "voted"), "--votes", "2"])
    assert voted.exit_code == 0, voted.output
    assert read_labels(tmp_path / "voted" / "test.labels").size == labels.size
    no_votes = runner.invoke(app, [*predict, "--out", str(tmp_path / "v0"), "--votes", "0"])
    assert no_votes.exit_code == 2 and not (tmp_path / "v0").exists()
    no_gpu = runner.invoke(app, [*predict, "--out", str(tmp_path / "x"), "--device", "cuda"])
    assert no_gpu.exit_code in (0, 2)  # 0 only where a GPU exists
    if no_gpu.exit_code == 2:
        assert "no CUDA GPU" in no_gpu.output

    archive = tmp_path / "sub.zip"
    result = runner.invoke(
        app,
        [
            "baseline",
            "randla",
            "predict",
            "--data",
            str(randla_scans),
            "--model",
            str(model),
            "--out",
            str(archive),
        ],
    )
    assert result.exit_code == 0, result.output
    with zipfile.ZipFile(archive) as opened:
        assert sorted(opened.namelist()) == ["test.labels", "train.labels"]
    assert "submit it with" in result.output

    scores = tmp_path / "cv.json"
    cv = ["baseline", "randla", "cv", "--data", str(randla_scans), "--config", str(config)]
    result = runner.invoke(app, [*cv, "--folds", "2", "--batches", "1", "--out", str(scores)])
    assert result.exit_code == 0, result.output
    document = json.loads(scores.read_text())
    assert document["n_folds"] == 2 and len(document["folds"]) == 2
    assert sum(f["n_points"] for f in document["folds"]) == 4800
    bad = runner.invoke(app, [*cv, "--folds", "3"])
    assert bad.exit_code == 2 and "expected 2..2 folds" in bad.output
