from __future__ import annotations

import json
import socket
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from semantic3d.cli.app import app

runner = CliRunner()


#: Top-level modules of the extras `make demo` does not install (pyproject's ``demo``).
NOT_IN_THE_DEMO = ("torch", "dask", "distributed", "skimage", "maxflow", "py7zr", "lightgbm")

_WITHOUT_OTHER_EXTRAS = f"""
import sys
from importlib.abc import MetaPathFinder

class Absent(MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.partition(".")[0] in {NOT_IN_THE_DEMO!r}:
            raise ModuleNotFoundError(f"No module named {{name!r}}", name=name)
        return None

sys.meta_path.insert(0, Absent())
from semantic3d.cli.app import main
main()
"""


def test_the_demo_extra_leaves_out_the_heavy_ones() -> None:
    import tomllib

    project = tomllib.loads((Path(__file__).parents[2] / "pyproject.toml").read_text())
    extras = project["project"]["optional-dependencies"]
    (demo,) = extras["demo"]
    wanted = demo.removeprefix("semantic3d[").removesuffix("]").split(",")
    requirements = " ".join(r for extra in wanted for r in extras[extra])
    for heavy in ("torch", "dask", "scikit-image", "PyMaxflow", "lightgbm", "py7zr"):
        assert heavy not in requirements


@pytest.mark.slow
def test_demo_runs_end_to_end_without_real_data_and_the_other_extras(tmp_path: Path) -> None:
    out = tmp_path / "demo"
    args = ["demo", "--out", str(out), "--data", str(tmp_path / "none"), "--points", "80000"]
    result = subprocess.run(
        [sys.executable, "-c", _WITHOUT_OTHER_EXTRAS, *args],
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    assert "no real samples" in result.stdout
    report = json.loads((out / "result.json").read_text())
    assert report["challenge"] == "demo"
    # The baseline must beat a constant "man-made terrain" answer by a wide margin.
    assert report["scores"]["mean_iou"] > 0.4
    html = (out / "report.html").read_text()
    assert "<img" in html and "covariance baseline" in html
    assert sorted(p.name for p in (out / "submission").iterdir()) == ["square_station2.labels"]


@pytest.mark.slow
def test_demo_serve_scores_the_demo_submission_on_the_server(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # everything `make demo` runs up to the point where the server starts listening
    from semantic3d.server import serving

    started: list[object] = []
    monkeypatch.setattr(serving, "run_server", lambda app, *args, **options: started.append(app))
    out = tmp_path / "demo"
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    served = runner.invoke(
        app,
        ["demo", "--out", str(out), "--data", str(tmp_path / "none"), "--points", "60000",
         "--serve", "--port", str(port)],
    )  # fmt: skip
    assert served.exit_code == 0, served.output
    assert "invalid submission" not in served.output and "warning" not in served.output
    assert "leaderboard" in served.output and len(started) == 1
    assert not (out / "server-data" / "demo-predictions.zip").exists()


@pytest.mark.slow
def test_demo_converts_the_real_samples(tmp_path: Path, shared_data: Path) -> None:
    data = tmp_path / "data" / "oakland"
    data.mkdir(parents=True)
    source = shared_data / "oakland" / "oakland_part2_ac"
    for suffix in (".txt", ".labels"):
        (data / f"oakland_part2_ac{suffix}").symlink_to(source.with_suffix(suffix))
    out = tmp_path / "demo"
    result = runner.invoke(
        app,
        ["demo", "--out", str(out), "--data", str(tmp_path / "data"), "--points", "60000"],
    )
    assert result.exit_code == 0, result.output
    samples = out / "samples"
    assert (samples / "oakland_part2_ac.las").stat().st_size > 0
    assert (samples / "oakland_part2_ac.ply").stat().st_size > 0
    assert (samples / "oakland_part2_ac.cache" / "meta.json").is_file()
