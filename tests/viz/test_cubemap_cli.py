"""``semantic3d cubemap`` through typer's CliRunner."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import typer
from typer.testing import CliRunner

from semantic3d.cli import cubemap as cubemap_cli
from semantic3d.io.ascii import write_ascii_points
from tests.factories import random_cloud

runner = CliRunner()


@pytest.fixture(scope="module")
def app() -> typer.Typer:
    application = typer.Typer()

    @application.callback()
    def _root() -> None:
        """Test root."""

    cubemap_cli.register(application)
    return application


@pytest.fixture(scope="module")
def scan(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("scan")
    path = folder / "scan.txt"
    write_ascii_points(path, [random_cloud(400, seed=1)], labels_path=folder / "scan.labels")
    return path


def test_renders_faces_from_the_given_station(app: typer.Typer, scan: Path, tmp_path: Path) -> None:
    out = tmp_path / "faces"
    args = ["cubemap", str(scan), "--station", "1,2,3", "--size", "16", "--out", str(out)]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    assert "[option]" in result.output
    meta = json.loads((out / "cubemap.json").read_text())
    assert meta["station_m"] == [1.0, 2.0, 3.0] and meta["size_px"] == 16
    assert np.load(out / "index.npy").shape == (6, 16, 16)
    assert (out / "labels_pz.png").is_file()
    again = runner.invoke(app, args)
    assert again.exit_code == 2
    assert "already exists" in again.output and "--overwrite" in again.output
    assert runner.invoke(app, [*args, "--overwrite"]).exit_code == 0


def test_bad_station_string_is_one_error_line(app: typer.Typer, scan: Path, tmp_path: Path) -> None:
    result = runner.invoke(
        app, ["cubemap", str(scan), "--station", "1;2;3", "--out", str(tmp_path / "x")]
    )
    assert result.exit_code == 2
    assert "station: expected x,y,z" in result.output
    assert not (tmp_path / "x").exists()


def test_estimated_station_without_option_or_sidecar(
    app: typer.Typer, scan: Path, tmp_path: Path
) -> None:
    result = runner.invoke(app, ["cubemap", str(scan), "--size", "8", "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    assert "[estimated]" in result.output


def test_missing_scan(app: typer.Typer, tmp_path: Path) -> None:
    result = runner.invoke(app, ["cubemap", str(tmp_path / "none.txt"), "--out", str(tmp_path)])
    assert result.exit_code == 2
    assert "none.txt" in result.output
