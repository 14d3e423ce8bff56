"""``semantic3d baseline covariance train | predict | cv`` through typer's CliRunner."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import typer
from typer.testing import CliRunner

from semantic3d.cli import baseline
from semantic3d.io.labels import count_labels

runner = CliRunner()


@pytest.fixture(scope="module")
def app() -> typer.Typer:
    application = typer.Typer()

    @application.callback()
    def _root() -> None:
        """Test root."""

    baseline.register(application)
    return application


@pytest.fixture(scope="module")
def config_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("cfg") / "small.toml"
    path.write_text(
        "[features]\nbase_voxel_size_m = 0.1\nn_levels = 5\n"
        "[forest]\nn_estimators = 8\nmax_depth = 10\n"
        "[sampling]\npoints_per_class = 200\n"
        "[grid_search]\nn_estimators = [4]\nmax_depth = [3, 8]\nmin_samples_leaf = [1]\n"
    )
    return path


def test_train_then_predict(
    app: typer.Typer, scene_dir: Path, config_file: Path, tmp_path: Path
) -> None:
    model = tmp_path / "m.s3d"
    result = runner.invoke(
        app,
        [
            "baseline",
            "covariance",
            "train",
            "--data",
            str(scene_dir),
            "--scans",
            "train_a,train_b",
            "--config",
            str(config_file),
            "--out",
            str(model),
            "--seed",
            "3",
        ],
    )
    assert result.exit_code == 0, result.output
    assert "trained on 2 scans" in result.output and model.is_file()
    labels = tmp_path / "out.labels"
    result = runner.invoke(
        app,
        [
            "baseline",
            "covariance",
            "predict",
            str(scene_dir / "test.txt"),
            "--model",
            str(model),
            "--out",
            str(labels),
        ],
    )
    assert result.exit_code == 0, result.output
    assert count_labels(labels) == count_labels(scene_dir / "test.labels")
    assert json.loads((tmp_path / "out.labels.json").read_text())["training_scans"] == [
        "train_a",
        "train_b",
    ]


def test_train_with_grid_search_fits_and_records_the_chosen_forest(
    app: typer.Typer, scene_dir: Path, config_file: Path, tmp_path: Path
) -> None:
    from semantic3d.baselines.covariance.persistence import load_model, read_model_header

    model_path = tmp_path / "m.s3d"
    args = ["--data", str(scene_dir), "--config", str(config_file), "--out", str(model_path)]
    result = runner.invoke(app, ["baseline", "covariance", "train", *args, "--grid-search"])
    assert result.exit_code == 0, result.output
    assert "grid search (jaccard_macro, 3 folds grouped by scan) chose" in result.output
    header = read_model_header(model_path)
    search = header["grid_search"]
    assert search["n_splits"] == 3 and len(search["results"]) == 2  # depth 3 and 8
    chosen = search["best_params"]
    assert chosen["max_depth"] in (3, 8) and chosen["n_estimators"] == 4
    assert header["config"]["forest"]["max_depth"] == chosen["max_depth"]
    assert header["config"]["forest"]["n_estimators"] == 4  # not the file's 8
    model = load_model(model_path)
    assert model.classifier.params["max_depth"] == chosen["max_depth"]
    assert model.grid_search is not None and model.grid_search.best_params == chosen


def test_cv_prints_the_grid_and_writes_json(
    app: typer.Typer, scene_dir: Path, config_file: Path, tmp_path: Path
) -> None:
    out = tmp_path / "cv.json"
    result = runner.invoke(
        app,
        [
            "baseline",
            "covariance",
            "cv",
            "--data",
            str(scene_dir),
            "--config",
            str(config_file),
            "--out",
            str(out),
        ],
    )
    assert result.exit_code == 0, result.output
    assert "3 folds grouped by scan" in result.output
    saved = json.loads(out.read_text())
    assert saved["n_splits"] == 3 and len(saved["results"]) == 2


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["train", "--data", "{scenes}", "--scans", "nope", "--out", "{tmp}/m"], "not found"),
        (["predict", "{scenes}/test.txt", "--model", "{scenes}/test.labels"], "not a semantic3d"),
        (["cv", "--data", "{scenes}", "--config", "{tmp}/absent.toml"], "cannot read the config"),
    ],
)
def test_errors_print_one_red_line_and_exit_2(
    app: typer.Typer, scene_dir: Path, tmp_path: Path, args: list[str], message: str
) -> None:
    filled = [a.format(scenes=scene_dir, tmp=tmp_path) for a in args]
    result = runner.invoke(app, ["baseline", "covariance", *filled])
    assert result.exit_code == 2
    assert message in result.output and "Traceback" not in result.output
