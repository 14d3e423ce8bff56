"""``semantic3d baseline covariance predict``: safe default output, whole splits, zips, the
predict → evaluate flow, and interruption."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
from typer.testing import CliRunner

from semantic3d.baselines.common.submission import (
    ScanToLabel,
    SubmissionLayoutError,
    find_scans_to_label,
)
from semantic3d.baselines.covariance.model import CovarianceModel
from semantic3d.baselines.covariance.persistence import save_model
from semantic3d.baselines.covariance.predict import predict_scans
from semantic3d.baselines.covariance.training import (
    build_training_set,
    find_labelled_scans,
    fit_model,
)
from semantic3d.cli.app import app
from semantic3d.core.errors import OutputExistsError
from semantic3d.datasets import Semantic3D
from semantic3d.evaluation import load_challenge
from semantic3d.io.labels import count_labels
from tests.baselines.conftest import SMALL_CONFIG, write_scan
from tests.baselines.scene import make_street_scene

runner = CliRunner()


@pytest.fixture(scope="module")
def model(scene_dir: Path) -> CovarianceModel:
    scans = find_labelled_scans(scene_dir, names=["train_a"])
    return fit_model(build_training_set(scans, config=SMALL_CONFIG), config=SMALL_CONFIG)


@pytest.fixture(scope="module")
def model_file(model: CovarianceModel, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return save_model(model, tmp_path_factory.mktemp("model") / "m.s3d")


@pytest.fixture
def data(tmp_path: Path) -> Path:
    """Two small labelled scans, ``a`` and ``b``."""
    folder = tmp_path / "data"
    for name, seed in (("a", 31), ("b", 32)):
        write_scan(folder, name, make_street_scene(seed, size_m=12.0, spacing_m=0.25))
    return folder


def _predict(*args: str) -> tuple[int, str]:
    result = runner.invoke(app, ["baseline", "covariance", "predict", *args])
    return result.exit_code, result.output


def test_predict_without_out_never_touches_the_ground_truth(
    model_file: Path, data: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    truth = (data / "a.labels").read_bytes()
    code, output = _predict(str(data / "a.txt"), "--model", str(model_file))
    assert code == 0, output
    assert (data / "a.labels").read_bytes() == truth
    assert sorted(p.name for p in data.iterdir()) == ["a.labels", "a.txt", "b.labels", "b.txt"]
    written = tmp_path / "predictions" / "a.labels"
    assert count_labels(written) == count_labels(data / "a.labels")
    assert json.loads((tmp_path / "predictions" / "a.labels.json").read_text())["n_points"] > 0
    # a second run refuses to replace the first one's output, unless told
    before = written.read_bytes()
    code, output = _predict(str(data / "a.txt"), "--model", str(model_file))
    assert code == 2
    assert "a.labels: already exists" in output and "--overwrite" in output
    assert written.read_bytes() == before
    code, output = _predict(str(data / "a.txt"), "--model", str(model_file), "--overwrite")
    assert code == 0, output


def test_a_labels_out_names_the_file(model_file: Path, data: Path, tmp_path: Path) -> None:
    out = tmp_path / "x" / "mine.labels"
    code, output = _predict(str(data / "b.txt"), "--model", str(model_file), "--out", str(out))
    assert code == 0, output
    assert count_labels(out) == count_labels(data / "b.labels")
    assert (out.parent / "mine.labels.json").is_file()
    code, output = _predict(
        str(data / "b.txt"), "--model", str(model_file), "--out", str(data / "b.labels")
    )
    assert code == 2 and "is the ground truth of the scan b.txt" in output


@pytest.mark.parametrize(
    "out_form", ["folder", "labels-file", "hard-link", "other-scan"], ids=lambda f: f
)
def test_a_prediction_never_replaces_the_ground_truth_even_with_overwrite(
    model_file: Path, data: Path, tmp_path: Path, out_form: str
) -> None:
    before = {path.name: path.read_bytes() for path in data.iterdir()}
    if out_form == "folder":  # --data into the scans' own folder
        args = ["--data", str(data), "--out", str(data)]
    elif out_form == "labels-file":  # one scan onto its own NAME.labels
        args = [str(data / "a.txt"), "--out", str(data / "a.labels")]
    elif out_form == "hard-link":  # another name of the same file
        link = tmp_path / "elsewhere" / "a.labels"
        link.parent.mkdir()
        os.link(data / "a.labels", link)
        args = ["--data", str(data), "--out", str(link.parent)]
    else:  # one scan's output over another scan's ground truth
        args = [str(data / "a.txt"), "--out", str(data / "b.labels")]
    code, output = _predict(*args, "--model", str(model_file), "--overwrite")
    assert code == 2
    lines = [line for line in output.splitlines() if line.strip()]
    assert len(lines) == 1 and "is the ground truth of the scan" in lines[0], output
    assert {path.name: path.read_bytes() for path in data.iterdir()} == before


def test_the_library_refuses_the_ground_truth_too(model: CovarianceModel, data: Path) -> None:
    from semantic3d.baselines.common.prediction import predict_scan
    from semantic3d.core.errors import GroundTruthOutputError

    truth = (data / "a.labels").read_bytes()
    with pytest.raises(GroundTruthOutputError, match=r"a\.labels: is the ground truth"):
        predict_scan(model, data / "a.txt", out_path=data / "a.labels", overwrite=True)
    scans = find_scans_to_label(data)
    with pytest.raises(GroundTruthOutputError, match="is the ground truth of the scan"):
        predict_scans(model, scans, data, overwrite=True)
    assert (data / "a.labels").read_bytes() == truth
    assert not (data / "a.labels.json").exists()


def test_predict_a_folder_then_evaluate_it_as_it_is(
    model_file: Path, data: Path, tmp_path: Path
) -> None:
    predictions = tmp_path / "predictions"
    code, output = _predict(
        "--data", str(data), "--model", str(model_file), "--out", str(predictions)
    )
    assert code == 0, output
    assert "2 scans" in output
    assert sorted(p.name for p in predictions.iterdir()) == [
        "a.labels",
        "a.labels.json",
        "b.labels",
        "b.labels.json",
    ]
    result = runner.invoke(app, ["evaluate", "--gt", str(data), "--pred", str(predictions)])
    assert result.exit_code == 0, result.output
    assert "labelled points scored" in result.output
    result = runner.invoke(app, ["validate", str(predictions), "--gt", str(data)])
    assert result.exit_code == 0, result.output
    assert "holds the 2 files" in " ".join(result.output.split())


def test_a_stray_json_in_a_zip_is_still_refused(data: Path, tmp_path: Path) -> None:
    archive = tmp_path / "sub.zip"
    with zipfile.ZipFile(archive, "w") as out:
        for name in ("a.labels", "b.labels"):
            out.write(data / name, arcname=name)
        out.write(data / "a.labels", arcname="a.labels.json")
    result = runner.invoke(app, ["validate", str(archive), "--gt", str(data)])
    assert result.exit_code == 1
    assert "unexpected file 'a.labels.json'" in result.output


def test_predict_a_split_into_a_zip_ready_to_submit(
    model_file: Path, data: Path, tmp_path: Path
) -> None:
    archive = tmp_path / "out" / "preds.zip"
    code, output = _predict("--data", str(data), "--model", str(model_file), "--out", str(archive))
    assert code == 0, output
    assert "semantic3d submit" in output and "--runtime-s" in output
    with zipfile.ZipFile(archive) as opened:
        assert sorted(opened.namelist()) == ["a.labels", "b.labels"]
    record = json.loads((tmp_path / "out" / "preds.zip.json").read_text())
    assert [scan["labels_path"] for scan in record["scans"]] == [
        f"{archive}:a.labels",
        f"{archive}:b.labels",
    ]
    assert sorted(p.name for p in archive.parent.iterdir()) == ["preds.zip", "preds.zip.json"]
    result = runner.invoke(app, ["validate", str(archive), "--gt", str(data)])
    assert result.exit_code == 0, result.output
    code, output = _predict("--data", str(data), "--model", str(model_file), "--out", str(archive))
    assert code == 2 and "preds.zip: already exists" in output


def test_a_challenge_split_gets_the_official_names(
    model_file: Path, data: Path, tmp_path: Path
) -> None:
    split = tmp_path / "reduced"
    split.mkdir()
    for files in Semantic3D(split).scans("reduced-8"):
        files.points_path.write_bytes((data / "a.txt").read_bytes())
    archive = tmp_path / "reduced-8.zip"
    code, output = _predict(
        "--data", str(split), "--challenge", "reduced-8", "--model", str(model_file),
        "--out", str(archive),
    )  # fmt: skip
    assert code == 0, output
    assert "--challenge reduced-8" in " ".join(output.split())
    with zipfile.ZipFile(archive) as opened:
        assert sorted(opened.namelist()) == sorted(
            load_challenge("reduced-8", ground_truth_root=None).submission_names
        )


def test_a_challenge_split_with_missing_scans_is_one_line(model_file: Path, data: Path) -> None:
    code, output = _predict(
        "--data", str(data), "--challenge", "semantic-8", "--model", str(model_file)
    )
    assert code == 2
    assert "expected the 15 scans of semantic-8, missing 15" in output
    assert len(output.strip().splitlines()) == 1


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (
            ["{data}/a.txt", "--data", "{data}"],
            "expected one SCAN argument or --data DIR, found both",
        ),
        ([], "expected one SCAN argument or --data DIR, found neither"),
        (["{data}/a.txt", "--challenge", "reduced-8"], "--challenge applies to --data"),
        (["--data", "{data}", "--out", "{data}/x.labels"], "--out is a folder or a .zip"),
        (["{data}/missing.txt"], "expected a scan file"),
        (["--data", "{data}/a.txt"], "is a file"),
        (["--data", "{empty}"], "expected NAME.txt scans, found none"),
    ],
)
def test_bad_predict_arguments_exit_2_with_one_line(
    model_file: Path, data: Path, tmp_path: Path, args: list[str], message: str
) -> None:
    (tmp_path / "empty").mkdir()
    filled = [a.format(data=data, empty=tmp_path / "empty") for a in args]
    code, output = _predict(*filled, "--model", str(model_file))
    assert code == 2, output
    assert message in " ".join(output.split())
    assert "Traceback" not in output


def test_an_interrupted_zip_run_leaves_nothing(
    model: CovarianceModel, data: Path, tmp_path: Path
) -> None:
    scans = find_scans_to_label(data)

    def interrupt(index: int, done: int, total: int) -> None:
        if index == 1:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        predict_scans(model, scans, tmp_path / "out" / "p.zip", progress=interrupt)
    assert list((tmp_path / "out").iterdir()) == []
    # a folder keeps the scans finished before the interrupt, whole, and nothing partial
    with pytest.raises(KeyboardInterrupt):
        predict_scans(model, scans, tmp_path / "folder", progress=interrupt)
    assert sorted(p.name for p in (tmp_path / "folder").iterdir()) == ["a.labels", "a.labels.json"]


def test_the_library_refuses_existing_outputs_before_working(
    model: CovarianceModel, data: Path, tmp_path: Path
) -> None:
    (tmp_path / "b.labels.json").write_text("{}")
    scans = find_scans_to_label(data)
    with pytest.raises(OutputExistsError, match=r"b\.labels\.json: already exists"):
        predict_scans(model, scans, tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.labels.json", "data"]


def test_finding_scans_to_label(data: Path, tmp_path: Path) -> None:
    assert find_scans_to_label(data) == (
        ScanToLabel("a", data / "a.txt", "a.labels"),
        ScanToLabel("b", data / "b.txt", "b.labels"),
    )
    with pytest.raises(SubmissionLayoutError, match=r"expected a folder of NAME\.txt scans"):
        find_scans_to_label(tmp_path / "nowhere")
    with pytest.raises(
        SubmissionLayoutError, match="expected a challenge, one of semantic-8, reduced-8"
    ):
        find_scans_to_label(data, challenge="train")


def test_scans_labelled_in_parallel_give_the_same_files(
    model: CovarianceModel, data: Path, tmp_path: Path
) -> None:
    scans = find_scans_to_label(data)
    seen: list[int] = []
    alone = predict_scans(model, scans, tmp_path / "alone")
    together = predict_scans(
        model,
        scans,
        tmp_path / "together",
        parallel_scans=2,
        progress=lambda index, done, total: seen.append(index),
    )
    assert [run.scan for run in together.runs] == [run.scan for run in alone.runs]
    for scan in scans:
        assert (tmp_path / "together" / scan.output_name).read_bytes() == (
            tmp_path / "alone" / scan.output_name
        ).read_bytes()
    assert set(seen) == {0, 1}
    zipped = predict_scans(model, scans, tmp_path / "p.zip", parallel_scans=3)
    with zipfile.ZipFile(tmp_path / "p.zip") as archive:
        assert archive.namelist() == ["a.labels", "b.labels"]
        assert archive.read("b.labels") == (tmp_path / "alone" / "b.labels").read_bytes()
    assert zipped.n_points == alone.n_points


def test_a_failing_scan_stops_a_parallel_run_and_leaves_nothing_partial(
    model: CovarianceModel, data: Path, tmp_path: Path
) -> None:
    (data / "b.txt").write_text("1 2 3 0 0 0 0\n1 2\n")
    scans = find_scans_to_label(data)
    with pytest.raises(ValueError, match=r"b\.txt: line 2: expected 7 columns"):
        predict_scans(model, scans, tmp_path / "out", parallel_scans=2)
    # only complete files: `a` if it finished before the error, never a staged one
    assert {p.name for p in (tmp_path / "out").iterdir()} <= {"a.labels", "a.labels.json"}
    with pytest.raises(ValueError, match=r"b\.txt: line 2"):
        predict_scans(model, scans, tmp_path / "p.zip", parallel_scans=2)
    assert not (tmp_path / "p.zip").exists()
    with pytest.raises(ValueError, match="parallel_scans: expected at least 1, found 0"):
        predict_scans(model, scans, tmp_path / "none", parallel_scans=0)


def test_an_interrupted_parallel_run_leaves_nothing(
    model: CovarianceModel, data: Path, tmp_path: Path
) -> None:
    scans = find_scans_to_label(data)

    def interrupt(index: int, done: int, total: int) -> None:
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        predict_scans(
            model, scans, tmp_path / "out" / "p.zip", progress=interrupt, parallel_scans=2
        )
    assert list((tmp_path / "out").iterdir()) == []


def test_predict_a_folder_with_parallel_scans_option(
    model_file: Path, data: Path, tmp_path: Path
) -> None:
    code, output = _predict(
        "--model",
        str(model_file),
        "--data",
        str(data),
        "--out",
        str(tmp_path / "two"),
        "--parallel-scans",
        "2",
    )
    assert code == 0, output
    code, output = _predict(
        "--model",
        str(model_file),
        "--data",
        str(data),
        "--out",
        str(tmp_path / "one"),
        "--parallel-scans",
        "1",
    )
    assert code == 0, output
    for name in ("a.labels", "b.labels"):
        assert (tmp_path / "two" / name).read_bytes() == (tmp_path / "one" / name).read_bytes()
    code, output = _predict(
        "--model", str(model_file), "--data", str(data), "--parallel-scans", "0"
    )
    assert code == 2
    assert "--parallel-scans" in output


def test_parallel_scans_fall_back_to_one_where_numba_is_not_thread_safe(
    model_file: Path, data: Path, tmp_path: Path
) -> None:
    # numba's workqueue layer must not be entered from two threads at once
    env = {**os.environ, "NUMBA_THREADING_LAYER": "workqueue"}
    command = [
        sys.executable, "-m", "semantic3d", "baseline", "covariance", "predict",
        "--model", str(model_file), "--data", str(data), "--out", str(tmp_path / "out"),
        "--parallel-scans", "2",
    ]  # fmt: skip
    done = subprocess.run(command, capture_output=True, text=True, env=env, timeout=300)
    assert done.returncode == 0, done.stderr
    assert "labelling one scan at a time (numba's threading layer" in " ".join(done.stdout.split())
    assert sorted(p.name for p in (tmp_path / "out").glob("*.labels")) == ["a.labels", "b.labels"]


class _CountingPredictor:
    """Wraps a model and records how many scans it was labelling at once."""

    def __init__(self, model: CovarianceModel, max_parallel_scans: int | None) -> None:
        import threading

        self.model = model
        self.active = 0
        self.most = 0
        self._lock = threading.Lock()
        if max_parallel_scans is not None:
            self.max_parallel_scans = max_parallel_scans

    @property
    def training_scans(self) -> tuple[str, ...]:
        return self.model.training_scans

    @property
    def chunk_size(self) -> int:
        return self.model.chunk_size

    def iter_labelled_blocks(self, chunks, *, workdir):  # type: ignore[no-untyped-def]
        import time

        with self._lock:
            self.active += 1
            self.most = max(self.most, self.active)
        try:
            time.sleep(0.3)  # long enough for another scan's thread to start meanwhile
            yield from self.model.iter_labelled_blocks(chunks, workdir=workdir)
        finally:
            with self._lock:
                self.active -= 1


@pytest.mark.parametrize(("declared", "most"), [(None, 2), (1, 1), (4, 2)])
def test_a_predictors_max_parallel_scans_caps_the_scans_labelled_at_once(
    model: CovarianceModel, data: Path, tmp_path: Path, declared: int | None, most: int
) -> None:
    from semantic3d.baselines.common.prediction import parallel_scans_limit

    predictor = _CountingPredictor(model, declared)
    assert parallel_scans_limit(predictor) == declared
    scans = find_scans_to_label(data)
    predict_scans(predictor, scans, tmp_path / "out", parallel_scans=2)
    assert predictor.most == most
    alone = predict_scans(model, scans, tmp_path / "alone")
    assert [run.n_points for run in alone.runs] == [
        count_labels(tmp_path / "out" / scan.output_name) for scan in scans
    ]
