from __future__ import annotations

from typer.testing import CliRunner

from semantic3d import __version__
from semantic3d.cli.app import app

runner = CliRunner()


def test_version_and_help() -> None:
    result = runner.invoke(app, ["--version"])
    assert result.exit_code == 0
    assert result.stdout.strip() == f"semantic3d {__version__}"
    result = runner.invoke(app, ["--help"])
    assert result.exit_code == 0
    assert "semantic3D.net" in result.stdout
