"""Every writer command refuses an existing output unless --overwrite; one option name per
quantity; counted nouns agree with their count; messages keep their brackets."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from semantic3d.cli.app import app
from semantic3d.cli.console import fail, plural

runner = CliRunner()


@pytest.fixture
def challenge(tmp_path: Path) -> tuple[Path, Path]:
    """A one-scan custom challenge: (ground-truth folder, prediction folder)."""
    gt, pred = tmp_path / "gt", tmp_path / "pred"
    gt.mkdir()
    pred.mkdir()
    (gt / "scan.labels").write_text("".join(f"{i % 9}\n" for i in range(90)))
    (pred / "scan.labels").write_text("".join(f"{1 + i % 8}\n" for i in range(90)))
    return gt, pred


def _one_error_line(output: str) -> str:
    lines = [line for line in output.splitlines() if line.strip()]
    assert len(lines) == 1, output
    return lines[0]


@pytest.mark.parametrize("option", ["--json", "--markdown"])
def test_evaluate_refuses_to_replace_a_report(
    challenge: tuple[Path, Path], tmp_path: Path, option: str
) -> None:
    gt, pred = challenge
    report = tmp_path / "report.out"
    report.write_text("keep me")
    args = ["evaluate", "--gt", str(gt), "--pred", str(pred), option, str(report)]
    result = runner.invoke(app, args)
    assert result.exit_code == 2
    line = _one_error_line(result.stderr)
    assert "report.out: already exists" in line and "--overwrite" in line
    assert report.read_text() == "keep me"
    result = runner.invoke(app, [*args, "--overwrite"])
    assert result.exit_code == 0, result.output
    assert report.read_text() != "keep me"


def test_runtime_has_one_name_and_the_old_one_still_works(
    challenge: tuple[Path, Path], tmp_path: Path
) -> None:
    gt, pred = challenge
    for option, value in (("--runtime-s", "12.5"), ("--runtime", "7")):
        out = tmp_path / f"{option}.json"
        result = runner.invoke(
            app,
            ["evaluate", "--gt", str(gt), "--pred", str(pred), option, value, "--json", str(out)],
        )
        assert result.exit_code == 0, result.output
        assert json.loads(out.read_text())["method"]["runtime_s"] == float(value)
    help_text = runner.invoke(app, ["evaluate", "--help"], terminal_width=200).output
    assert "--runtime-s" in help_text and "--runtime " not in help_text
    assert "--runtime-s" in runner.invoke(app, ["submit", "--help"], terminal_width=200).output


def test_one_file_is_singular(challenge: tuple[Path, Path]) -> None:
    gt, pred = challenge
    result = runner.invoke(app, ["validate", str(pred), "--gt", str(gt)])
    assert result.exit_code == 0, result.output
    assert "holds the 1 file of" in " ".join(result.output.split())


def test_plural() -> None:
    assert [plural(n, "scan") for n in (0, 1, 2, 1500)] == [
        "0 scans",
        "1 scan",
        "2 scans",
        "1,500 scans",
    ]


def test_error_lines_keep_brackets(capsys: pytest.CaptureFixture[str]) -> None:
    fail("needs pip install 'semantic3d[las]' [bold]not markup[/]")
    assert "pip install 'semantic3d[las]' [bold]not markup[/]" in capsys.readouterr().err


def test_stats_refuses_to_replace_a_plot(challenge: tuple[Path, Path], tmp_path: Path) -> None:
    gt, _ = challenge
    plot = tmp_path / "p.png"
    plot.write_bytes(b"old")
    result = runner.invoke(app, ["stats", str(gt), "--plot", str(plot)])
    assert result.exit_code == 2
    assert "p.png: already exists" in _one_error_line(result.stderr)
    assert plot.read_bytes() == b"old"


def test_simulate_refuses_to_replace_an_earlier_simulation(tmp_path: Path) -> None:
    args = ["simulate", "--scene", "street", "--points", "2000", "--out", str(tmp_path)]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    first = (tmp_path / "street_station1.labels").read_bytes()
    result = runner.invoke(app, [*args, "--seed", "5"])
    assert result.exit_code == 2
    line = _one_error_line(result.stderr)
    assert "street_station1.txt: already exists (and 2 other outputs)" in line
    assert (tmp_path / "street_station1.labels").read_bytes() == first
    result = runner.invoke(app, [*args, "--seed", "5", "--overwrite"])
    assert result.exit_code == 0, result.output
    assert (tmp_path / "street_station1.labels").read_bytes() != first


def test_train_refuses_to_replace_a_model(tmp_path: Path) -> None:
    (tmp_path / "m.s3d").write_bytes(b"a model")
    result = runner.invoke(
        app,
        [
            "baseline",
            "covariance",
            "train",
            "--data",
            str(tmp_path),
            "--out",
            str(tmp_path / "m.s3d"),
        ],
    )
    assert result.exit_code == 2
    assert "m.s3d: already exists" in _one_error_line(result.stderr)
