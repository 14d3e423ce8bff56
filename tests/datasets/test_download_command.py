"""``semantic3d download`` through typer's CliRunner, against a local HTTP mirror."""

from __future__ import annotations

from pathlib import Path

from typer.testing import CliRunner

from semantic3d.cli.app import app
from semantic3d.datasets.registry import scan, scans
from semantic3d.datasets.semantic3d import Semantic3D

runner = CliRunner()


def test_download_a_split(tmp_path: Path, full_mirror, benchmark_files) -> None:
    result = runner.invoke(
        app,
        [
            "download",
            "--split",
            "reduced-8",
            "--to",
            str(tmp_path),
            "--base-url",
            full_mirror.base_url,
        ],
    )

    assert result.exit_code == 0, result.output
    assert "4 scans downloaded, 0 already present, 0 failed" in result.output
    for info in scans("reduced-8"):
        assert (tmp_path / info.points.filename).read_bytes() == (
            benchmark_files.contents[info.points.filename]
        )


def test_failures_exit_non_zero_and_are_listed(tmp_path: Path, full_mirror) -> None:
    failing = scan("sg27_station10_reduced")
    del full_mirror.files[full_mirror.url_path(failing.points.archive)]

    result = runner.invoke(
        app,
        [
            "download",
            "--split",
            "reduced-8",
            "--to",
            str(tmp_path),
            "--base-url",
            full_mirror.base_url,
        ],
    )

    assert result.exit_code == 2
    assert "3 scans downloaded, 0 already present, 1 failed" in result.output
    assert "1 of 4 scans failed to download" in result.output
    assert f"{failing.name}: " in result.output
    assert "HTTP 404" in result.output
    assert [info.name for info in Semantic3D(tmp_path).missing("reduced-8")] == [failing.name]


def test_check_lists_presence_without_downloading(tmp_path: Path, full_mirror) -> None:
    info = scan("birdfountain_station1")
    (tmp_path / info.points.filename).write_bytes(b"0 0 0 0 0 0 0\n")

    result = runner.invoke(
        app,
        [
            "download",
            "--split",
            "all",
            "--to",
            str(tmp_path),
            "--base-url",
            full_mirror.base_url,
            "--check",
        ],
    )

    assert result.exit_code == 0, result.output
    assert "1 complete, 33 missing" in result.output
    assert full_mirror.requests == []


def test_unknown_split_is_a_usage_error(tmp_path: Path) -> None:
    result = runner.invoke(app, ["download", "--split", "test", "--to", str(tmp_path)])

    assert result.exit_code == 2
    assert "'test' is not one of" in result.output


def test_a_wait_before_a_retry_shows_on_the_archive_s_line() -> None:
    from rich.progress import Progress

    from semantic3d.cli.download import _ProgressTasks
    from semantic3d.datasets.download import DownloadProgress

    with Progress() as bar:
        tasks = _ProgressTasks(bar)
        tasks(DownloadProgress("http://m/a.7z", "a.7z", 0, 100))
        tasks(DownloadProgress("http://m/a.7z", "a.7z", 0, None, "HTTP 503; retry 1/5 in 1 s"))
        (task,) = bar.tasks
        assert task.description == "a: HTTP 503; retry 1/5 in 1 s"
        assert task.total == 100  # the wait does not forget the size
        tasks(DownloadProgress("http://m/a.7z", "a.7z", 40, 100))
        assert task.description == "a" and task.completed == 40
