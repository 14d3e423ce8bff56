"""The validate / evaluate / stats / agreement commands through typer's CliRunner."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from semantic3d.cli.app import app
from semantic3d.cli.console import console
from semantic3d.io.ascii import write_ascii_points
from tests.evaluation.conftest import Scans, labels_bytes, overlapping_scans, write_zip

runner = CliRunner()


@pytest.fixture(autouse=True)
def wide_console(monkeypatch: pytest.MonkeyPatch) -> None:
    """Render rich tables at 250 columns so that cells are not wrapped or elided."""
    monkeypatch.setattr(console, "_width", 250)


def test_validate_valid_submission(scans: Scans, tmp_path: Path) -> None:
    submission = write_zip(tmp_path / "s.zip", scans.pred_members())
    result = runner.invoke(app, ["validate", str(submission), "--gt", str(scans.gt_dir)])
    assert result.exit_code == 0, result.output
    assert "valid" in result.stdout and "2 files" in result.stdout


def test_validate_prints_every_problem_and_fails(scans: Scans, tmp_path: Path) -> None:
    members = {"Alpha.labels": b"1\n", "beta.labels": b"0\n", "[bold]x.labels": b"1\n"}
    submission = write_zip(tmp_path / "s.zip", members)
    result = runner.invoke(
        app, ["validate", str(submission), "--challenge", "custom", "--gt", str(scans.gt_dir)]
    )
    assert result.exit_code == 1
    output = " ".join(result.stderr.split())  # undo console wrapping
    assert "invalid submission" in output and "5 problems" in output
    assert "unexpected file '[bold]x.labels'" in output  # file names are not markup
    assert "did you mean 'alpha.labels'?" in output
    assert "missing file 'alpha.labels'" in output
    assert "beta.labels: line 1: expected an integer label value 1..8, found 0" in output
    assert "beta.labels: expected 80 lines" in output


def test_validate_official_challenge_without_ground_truth(tmp_path: Path) -> None:
    submission = write_zip(tmp_path / "s.zip", {"sg27_10-reduced.labels": b"1\n"})
    result = runner.invoke(app, ["validate", str(submission), "-c", "reduced-8"])
    assert result.exit_code == 1
    assert "missing file 'marketsquarefeldkirch4-reduced.labels'" in result.stderr


def test_custom_challenge_needs_ground_truth(tmp_path: Path) -> None:
    result = runner.invoke(app, ["validate", str(tmp_path)])
    assert result.exit_code == 2
    assert "--challenge custom needs --gt DIR" in result.stderr


def test_evaluate_writes_every_report(scans: Scans, tmp_path: Path) -> None:
    submission = scans.pred_folder(tmp_path / "s")
    out = tmp_path / "out"
    out.mkdir()
    result = runner.invoke(
        app,
        [
            "evaluate",
            "--gt",
            str(scans.gt_dir),
            "--pred",
            str(submission),
            "--json",
            str(out / "r.json"),
            "--report",
            str(out / "r.html"),
            "--markdown",
            str(out / "r.md"),
            "--method",
            "RandomGuess",
            "--runtime",
            "42",
        ],
    )
    assert result.exit_code == 0, result.output
    data = json.loads((out / "r.json").read_text())
    assert data["method"]["name"] == "RandomGuess"
    assert f"{data['scores']['mean_iou']:.3f}" in result.stdout
    assert "RandomGuess" in result.stdout and "42 s" in result.stdout
    # one row per class, names in full: readable in an 80-column terminal
    table = [line for line in result.stdout.splitlines() if line.startswith(("┃", "│"))]
    assert len(table) == 12 and max(len(line) for line in table) <= 80
    iou = data["scores"]["iou"]
    line = next(row for row in result.stdout.splitlines() if "IoU 8 cars" in row)
    assert (f"{iou[7]:.3f}" if iou[7] is not None else "absent") in line
    assert (out / "r.html").read_text().startswith("<!DOCTYPE html>")
    assert "| RandomGuess |" in (out / "r.md").read_text()


def test_evaluate_invalid_submission_exits_1(scans: Scans, tmp_path: Path) -> None:
    submission = write_zip(tmp_path / "s.zip", {"alpha.labels": labels_bytes([9] * 120)})
    result = runner.invoke(app, ["evaluate", "--gt", str(scans.gt_dir), "--pred", str(submission)])
    assert result.exit_code == 1
    assert "missing file 'beta.labels'" in result.stderr
    assert "alpha.labels: line 1" in result.stderr


def test_evaluate_official_challenge_with_incomplete_ground_truth(
    scans: Scans, tmp_path: Path
) -> None:
    result = runner.invoke(
        app,
        ["evaluate", "-c", "semantic-8", "--gt", str(scans.gt_dir), "--pred", str(tmp_path)],
    )
    assert result.exit_code == 2
    assert "expected ground truth of every semantic-8 scan, missing 15" in result.stderr


def test_stats_table_and_plot(tmp_path: Path) -> None:
    (tmp_path / "labels").mkdir()
    (tmp_path / "labels" / "bildstein_station3_xyz_intensity_rgb.labels").write_bytes(
        labels_bytes([1] * 5 + [8] * 2)
    )
    plot = tmp_path / "classes.png"
    result = runner.invoke(app, ["stats", str(tmp_path / "labels"), "--plot", str(plot)])
    assert result.exit_code == 0, result.output
    assert "train" in result.stdout
    table = [line for line in result.stdout.splitlines() if line.startswith(("┃", "│"))]
    assert len(table) == 12 and max(len(line) for line in table) <= 80
    cars = next(row for row in result.stdout.splitlines() if "cars" in row)
    assert cars.split()[-2] == "2"  # 2 points of class 8
    assert plot.read_bytes().startswith(b"\x89PNG")


def test_agreement_table_and_plot(tmp_path: Path) -> None:
    a, b = overlapping_scans()
    for name, cloud in (("a", a), ("b", b)):
        write_ascii_points(
            tmp_path / f"{name}.txt", [cloud], labels_path=tmp_path / f"{name}.labels"
        )
    plot = tmp_path / "agreement.png"
    args = [str(tmp_path / f) for f in ("a.txt", "a.labels", "b.txt", "b.labels")]
    result = runner.invoke(app, ["agreement", *args, "--max-distance", "0.05", "--plot", str(plot)])
    assert result.exit_code == 0, result.output
    assert "A→B" in result.stdout and "B→A" in result.stdout
    assert "9,400 (47.2 %)" in result.stdout  # 9400 of B's 19900 considered points
    assert "excluded" in result.stdout
    assert plot.read_bytes().startswith(b"\x89PNG")


@pytest.mark.parametrize("option", [["--max-distance", "0"], ["--tile-size", "0"]])
def test_agreement_rejects_bad_distances(tmp_path: Path, option: list[str]) -> None:
    files = []
    for name in ("a.txt", "a.labels", "b.txt", "b.labels"):
        (tmp_path / name).write_text("")
        files.append(str(tmp_path / name))
    result = runner.invoke(app, ["agreement", *files, *option])
    assert result.exit_code == 2
    assert "expected a positive --max-distance and --tile-size" in result.stderr
