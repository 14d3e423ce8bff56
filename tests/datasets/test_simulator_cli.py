"""``semantic3d simulate``: files written on success, one red line and exit 2 on bad input."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from semantic3d.cli.app import app
from semantic3d.io.labels import count_labels

runner = CliRunner()


def test_simulate_writes_scans_labels_and_sidecar(tmp_path: Path) -> None:
    out = tmp_path / "sim"
    result = runner.invoke(
        app,
        [
            "simulate",
            "--scene",
            "village",
            "--stations",
            "2",
            "--points",
            "20000",
            "--seed",
            "3",
            "--out",
            str(out),
        ],
    )
    assert result.exit_code == 0, result.output
    assert "village_station2.txt" in result.stdout and "man-made terrain" in result.stdout
    sidecar = json.loads((out / "village.json").read_text())
    assert sidecar["seed"] == 3 and len(sidecar["stations"]) == 2
    for record in sidecar["stations"]:
        assert count_labels(out / record["labels"]) == record["n_points"]
        lines = (out / record["points"]).read_text().splitlines()
        assert len(lines) == record["n_points"]
        assert len(lines[0].split()) == 7


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (
            ["--scene", "moon"],
            "unknown scene 'moon': expected one of village, street, square, railway",
        ),
        (["--stations", "0"], "stations: expected an integer in 1..3, found 0"),
        (["--stations", "4"], "stations: expected an integer in 1..3, found 4"),
        (["--points", "0"], "n_points: expected an integer in 1..2_000_000_000, found 0"),
        (["--points", "-3"], "found -3"),
    ],
)
def test_bad_arguments_exit_2_with_one_line(
    tmp_path: Path, arguments: list[str], message: str
) -> None:
    result = runner.invoke(app, ["simulate", "--out", str(tmp_path / "x"), *arguments])
    assert result.exit_code == 2
    assert message in result.output
    assert len(result.output.strip().splitlines()) == 1
    assert not (tmp_path / "x").exists()


def test_unwritable_output_exits_2_with_one_line(tmp_path: Path) -> None:
    (tmp_path / "taken").write_text("a file")
    result = runner.invoke(app, ["simulate", "--out", str(tmp_path / "taken" / "sub")])
    assert result.exit_code == 2
    assert "expected a writable output folder" in result.output
    assert len(result.output.strip().splitlines()) == 1
