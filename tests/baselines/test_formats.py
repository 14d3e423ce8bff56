"""Every format io reads can be trained on and classified, with the same results as ASCII."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from semantic3d.baselines.common import LabelledBlock, find_labelled_scans, predict_scan
from semantic3d.baselines.common.scans import LabelledScan, TrainingDataError
from semantic3d.baselines.covariance.model import CovarianceModel
from semantic3d.baselines.covariance.persistence import save_model
from semantic3d.baselines.covariance.training import build_training_set, fit_model
from semantic3d.core.errors import ShapeError
from semantic3d.io.formats import read_points, write_points
from semantic3d.io.labels import read_labels
from tests.baselines.conftest import SMALL_CONFIG

FORMATS = ["laz", "ply", "cache"]


@pytest.fixture(scope="module")
def model(scene_dir: Path) -> CovarianceModel:
    scans = find_labelled_scans(scene_dir, names=["train_a"])
    return fit_model(build_training_set(scans, config=SMALL_CONFIG), config=SMALL_CONFIG)


@pytest.fixture(scope="module")
def converted(scene_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """train_a and test as .laz, .ply and cache (labels inside), each in its own folder."""
    root = tmp_path_factory.mktemp("formats")
    for fmt in FORMATS:
        for name in ("train_a", "test"):
            cloud = read_points(scene_dir / f"{name}.txt", labels_path=scene_dir / f"{name}.labels")
            (root / fmt).mkdir(exist_ok=True)
            write_points(root / fmt / f"{name}.{fmt}", [cloud])
    return root


@pytest.mark.parametrize("fmt", FORMATS)
def test_predict_classifies_every_format_like_ascii(
    model: CovarianceModel, scene_dir: Path, converted: Path, tmp_path: Path, fmt: str
) -> None:
    expected = read_labels(
        predict_scan(model, scene_dir / "test.txt", out_path=tmp_path / "txt.labels").labels_path
    )
    run = predict_scan(model, converted / fmt / f"test.{fmt}", out_path=tmp_path / f"{fmt}.labels")
    np.testing.assert_array_equal(read_labels(run.labels_path), expected)


@pytest.mark.parametrize("fmt", FORMATS)
def test_training_reads_labels_inside_the_file(scene_dir: Path, converted: Path, fmt: str) -> None:
    scans = find_labelled_scans(converted / fmt, names=["train_a"])
    assert scans[0].labels_path is None and scans[0].points_path.parent == converted / fmt
    ascii_set = build_training_set(
        find_labelled_scans(scene_dir, names=["train_a"]), config=SMALL_CONFIG
    )
    other_set = build_training_set(scans, config=SMALL_CONFIG)
    np.testing.assert_array_equal(other_set.labels, ascii_set.labels)
    np.testing.assert_allclose(other_set.features, ascii_set.features, rtol=1e-5, atol=1e-5)


def test_cli_predicts_a_laz_scan(model: CovarianceModel, converted: Path, tmp_path: Path) -> None:
    from semantic3d.cli.app import app

    model_path = save_model(model, tmp_path / "model.s3d")
    out = tmp_path / "pred.labels"
    result = CliRunner().invoke(
        app,
        [
            "baseline", "covariance", "predict", "--model", str(model_path),
            str(converted / "laz" / "test.laz"), "--out", str(out),
        ],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    assert read_labels(out).size == read_points(converted / "laz" / "test.laz").n_points


def test_scans_without_labels_or_with_two_files_are_refused(
    scene_dir: Path, converted: Path, tmp_path: Path
) -> None:
    cloud = read_points(scene_dir / "test.txt")  # the .labels beside it is read too
    write_points(tmp_path / "bare.laz", [cloud.with_labels(None)])
    with pytest.raises(TrainingDataError, match=r"bare.laz: training needs labels"):
        find_labelled_scans(tmp_path)
    (tmp_path / "bare.laz").unlink()
    write_points(tmp_path / "twice.laz", [cloud])
    write_points(tmp_path / "twice.ply", [cloud])
    with pytest.raises(TrainingDataError, match=r"two scans named 'twice'"):
        find_labelled_scans(tmp_path)


class _Lazy:
    """A predictor that forgets half of the points."""

    training_scans = ("none",)
    chunk_size = 1000

    def iter_labelled_blocks(self, chunks, *, workdir):  # type: ignore[no-untyped-def]
        n = sum(chunk.n_points for chunk in chunks)
        yield LabelledBlock(np.arange(n // 2), np.ones(n // 2, np.uint8), n)


def test_a_predictor_that_leaves_points_unlabelled_writes_nothing(
    scene_dir: Path, tmp_path: Path
) -> None:
    with pytest.raises(ShapeError, match=r"expected a label for each of \d+ points, found \d+"):
        predict_scan(_Lazy(), scene_dir / "test.txt", out_path=tmp_path / "x.labels")
    assert list(tmp_path.iterdir()) == []


def test_labelled_scan_streams_labels_from_the_points_file(converted: Path) -> None:
    scan = LabelledScan("test", converted / "ply" / "test.ply")
    labels = np.concatenate(list(scan.iter_labels(chunk_size=700)))
    assert labels.size == read_points(scan.points_path).n_points
