"""Train and predict end to end on simulated scans; model files; the command line."""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np
import pytest
import typer
from PIL import Image
from typer.testing import CliRunner

from semantic3d.baselines.common.modelfile import ModelFileError
from semantic3d.baselines.common.scans import find_labelled_scans
from semantic3d.baselines.image.config import config_from_dict
from semantic3d.baselines.image.model import ImageModel, ImageVariant
from semantic3d.baselines.image.persistence import load_model, save_model
from semantic3d.baselines.image.predict import predict_image_scan
from semantic3d.baselines.image.training import render_scan, train_image_model
from semantic3d.cli import baseline
from semantic3d.core.errors import OutputExistsError
from semantic3d.io.labels import read_labels

TINY = {
    "preset": "small",
    "faces": {"size": 64, "chunk_size": 20_000},
    "words": {"n_words": 8, "sample_pixels": 4000},
    "rectangles": {"n_rectangles": 8, "max_offset_px": 10},
    "boosting": {"max_iter": 15, "pixels_per_class_per_face": 150},
    "unet": {"base_channels": 4, "depth": 2, "epochs": 2, "batch_size": 6, "crop_px": 32},
}
TINY_TOML = """preset = "small"
[faces]
size = 64
chunk_size = 20000
[words]
n_words = 8
sample_pixels = 4000
[rectangles]
n_rectangles = 8
max_offset_px = 10
[boosting]
max_iter = 15
pixels_per_class_per_face = 150
"""

runner = CliRunner()


@pytest.fixture(scope="module")
def boosted(simulated_dir: Path) -> ImageModel:
    scans = find_labelled_scans(simulated_dir, names=["street1"])
    return train_image_model(scans, config=config_from_dict(TINY), variant=ImageVariant.BOOSTED)


def _overall_accuracy(truth: np.ndarray, predicted: np.ndarray) -> float:
    labelled = truth > 0
    return float((truth[labelled] == predicted[labelled]).mean())


def test_boosted_beats_the_majority_class_on_another_scene(
    boosted: ImageModel, simulated_dir: Path, tmp_path: Path
) -> None:
    out = tmp_path / "street2.labels"
    result = predict_image_scan(
        boosted, simulated_dir / "street2.txt", out_path=out, faces_dir=tmp_path / "faces"
    )
    truth = read_labels(simulated_dir / "street2.labels")
    predicted = read_labels(out)
    assert predicted.size == truth.size
    assert 7 not in set(predicted.tolist())  # class 7 is ignored in 2D
    majority = np.bincount(truth[truth > 0]).max() / (truth > 0).sum()
    assert _overall_accuracy(truth, predicted) > majority + 0.05
    assert result.station.source == "estimated"
    record = json.loads(out.with_name("street2.labels.json").read_text())
    assert record["n_points"] == truth.size and record["training_scans"] == ["street1"]
    assert result.faces_dir == tmp_path / "faces" / "street2"
    picture = np.asarray(Image.open(result.faces_dir / "px.png"))
    assert picture.shape == (64, 3 * 64 + 2 * 4, 3)  # colour | truth | prediction
    with pytest.raises(OutputExistsError, match="already exists"):
        predict_image_scan(boosted, simulated_dir / "street2.txt", out_path=out)


def test_every_long_stage_reports_and_stepwise_boosting_is_one_fit(
    boosted: ImageModel, simulated_dir: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from semantic3d.baselines.image import segmenter

    monkeypatch.setattr(segmenter, "_BOOSTING_STEP", 1000)  # one fit of every round
    stages: dict[str, list[tuple[int, int]]] = {}
    scans = find_labelled_scans(simulated_dir, names=["street1"])
    once = train_image_model(
        scans,
        config=config_from_dict(TINY),
        variant=ImageVariant.BOOSTED,
        progress=lambda stage, done, total: stages.setdefault(stage, []).append((done, total)),
    )
    assert list(stages) == ["rendering", "descriptors", "words", "features", "boosting"]
    assert stages["words"][-1][0] == stages["words"][-1][1] and stages["boosting"] == [(15, 15)]
    rows = np.random.default_rng(0).random((500, once.segmenter.booster_.n_features_in_))
    np.testing.assert_array_equal(  # the fixture's booster was fitted 10 rounds at a time
        once.segmenter.booster_.predict_proba(rows),
        boosted.segmenter.booster_.predict_proba(rows),
    )


def test_model_round_trip_predicts_the_same(
    boosted: ImageModel, simulated_dir: Path, tmp_path: Path
) -> None:
    path = save_model(boosted, tmp_path / "m.s3d")
    loaded = load_model(path)
    assert loaded.label_values == boosted.label_values
    station = boosted.training_stations[0]
    for model, name in ((boosted, "a"), (loaded, "b")):
        predict_image_scan(
            model,
            simulated_dir / "street1.txt",
            out_path=tmp_path / f"{name}.labels",
            station=station,
        )
    np.testing.assert_array_equal(
        read_labels(tmp_path / "a.labels"), read_labels(tmp_path / "b.labels")
    )
    (tmp_path / "bad.s3d").write_bytes(b"S3DCOV1 {}\n")
    with pytest.raises(ModelFileError, match="not a semantic3d image model"):
        load_model(tmp_path / "bad.s3d")


def test_unet_variant_trains_and_round_trips(simulated_dir: Path, tmp_path: Path) -> None:
    pytest.importorskip("torch")
    scans = find_labelled_scans(simulated_dir, names=["street1"])
    model = train_image_model(scans, config=config_from_dict(TINY), variant=ImageVariant.UNET)
    loaded = load_model(save_model(model, tmp_path / "u.s3d"))
    assert loaded.variant is ImageVariant.UNET
    losses = loaded.segmenter.loss_history_  # type: ignore[union-attr]
    assert len(losses) == 2 and all(np.isfinite(losses)) and min(losses) > 0
    cubemap, _ = render_scan(scans[0], config=model.config)
    np.testing.assert_array_equal(model.segment_cubemap(cubemap), loaded.segment_cubemap(cubemap))
    predict_image_scan(loaded, simulated_dir / "street2.txt", out_path=tmp_path / "u.labels")
    predicted = read_labels(tmp_path / "u.labels")
    assert predicted.size == read_labels(simulated_dir / "street2.labels").size
    assert set(predicted.tolist()) <= set(model.label_values)


@pytest.fixture(scope="module")
def app() -> typer.Typer:
    application = typer.Typer()

    @application.callback()
    def _root() -> None:
        """Test root."""

    baseline.register(application)
    return application


def test_cli_train_predict_and_errors(
    app: typer.Typer, boosted: ImageModel, simulated_dir: Path, tmp_path: Path
) -> None:
    config = tmp_path / "tiny.toml"
    config.write_text(TINY_TOML)
    model = save_model(boosted, tmp_path / "m.s3d")
    refused = runner.invoke(
        app,
        ["baseline", "image", "train", "--data", str(simulated_dir), "--out", str(model)],
    )
    assert refused.exit_code == 2 and "already exists" in refused.output
    bad = runner.invoke(
        app,
        [
            "baseline",
            "image",
            "train",
            "--data",
            str(simulated_dir),
            "--config",
            str(config),
            "--preset",
            "paper",
            "--out",
            str(tmp_path / "n.s3d"),
        ],
    )
    assert bad.exit_code == 2 and "found both" in bad.output
    scan = simulated_dir / "street2.txt"
    out = tmp_path / "pred"
    predict = ["baseline", "image", "predict", str(scan), "--model", str(model), "--out", str(out)]
    wrong = runner.invoke(app, [*predict, "--station", "1,2"])
    assert wrong.exit_code == 2 and "station: expected x,y,z" in wrong.output
    done = runner.invoke(app, [*predict, "--station", "6,0,1.8"])
    assert done.exit_code == 0, done.output
    assert "[option]" in done.output
    assert sorted(p.name for p in out.iterdir()) == ["street2.labels", "street2.labels.json"]
    assert (
        read_labels(out / "street2.labels").size
        == read_labels(simulated_dir / "street2.labels").size
    )
    again = runner.invoke(app, predict)
    assert again.exit_code == 2 and "already exists" in again.output


def test_cli_predict_takes_every_baseline_s_out_forms(
    app: typer.Typer, boosted: ImageModel, simulated_dir: Path, tmp_path: Path
) -> None:
    from semantic3d.cli.app import app as semantic3d

    model = save_model(boosted, tmp_path / "m.s3d")
    predict = ["baseline", "image", "predict", "--model", str(model)]
    # one scan into a named .labels file (not a folder of that name), faces only when asked
    named = tmp_path / "pred" / "street2.labels"
    faces = tmp_path / "faces"
    done = runner.invoke(
        app,
        [*predict, str(simulated_dir / "street2.txt"), "--out", str(named), "--faces", str(faces)],
    )
    assert done.exit_code == 0, done.output
    assert named.is_file() and (named.parent / "street2.labels.json").is_file()
    assert sorted(p.name for p in named.parent.iterdir()) == [
        "street2.labels",
        "street2.labels.json",
    ]
    assert len(list((faces / "street2").glob("*.png"))) == 6
    data = tmp_path / "data"
    data.mkdir()
    for suffix in (".txt", ".labels"):
        (data / f"street2{suffix}").symlink_to(simulated_dir / f"street2{suffix}")
    evaluated = runner.invoke(
        semantic3d, ["evaluate", "--gt", str(data), "--pred", str(named.parent)]
    )
    assert evaluated.exit_code == 0, evaluated.output
    # every scan of a folder into a zip ready to submit
    archive = tmp_path / "submission.zip"
    zipped = runner.invoke(app, [*predict, "--data", str(data), "--out", str(archive)])
    assert zipped.exit_code == 0, zipped.output
    with zipfile.ZipFile(archive) as members:
        assert members.namelist() == ["street2.labels"]
    assert (tmp_path / "submission.zip.json").is_file() and "submit" in zipped.output
    # never onto the scans' own ground truth
    refused = runner.invoke(app, [*predict, "--data", str(data), "--out", str(data), "--overwrite"])
    assert refused.exit_code == 2 and "is the ground truth of the scan" in refused.output
