"""Every mistake a user can make on the command line is one red line and exit code 2: a
missing path or option (not click's usage block), a missing extra (named as the extra, not
as a module), an existing output (naming the flag, not the library's argument), a
truncated LAZ file (no library log lines before ours)."""

from __future__ import annotations

import logging
import subprocess
import sys
from pathlib import Path

import pytest

from semantic3d.cli.app import _this_package_or_critical
from semantic3d.core.errors import MissingExtraError, OutputExistsError, refuse_existing_paths


def _run(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "semantic3d", *args],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=120,
        check=False,
    )


def _one_line(result: subprocess.CompletedProcess[str]) -> str:
    lines = [line for line in (result.stdout + result.stderr).splitlines() if line.strip()]
    assert len(lines) == 1, result.stdout + result.stderr
    return lines[0]


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        (["info", "nope.txt"], "semantic3d info: invalid value for 'path': path 'nope.txt'"),
        (["convert"], "semantic3d convert: missing argument 'PATH'"),
        (["info", "--bogus", "x"], "semantic3d info: no such option: --bogus"),
        (["evaluate", "--gt", "absent", "--pred", "x"], "invalid value for '--gt'"),
    ],
)
def test_a_command_line_mistake_is_one_line(tmp_path: Path, args: list[str], expected: str) -> None:
    result = _run(*args, cwd=tmp_path)
    assert result.returncode == 2
    line = _one_line(result)
    assert line.startswith("error: ") and expected in line and "--help" in line


def test_help_and_a_bare_group_still_show_help(tmp_path: Path) -> None:
    shown = _run("info", "--help", cwd=tmp_path)
    assert shown.returncode == 0 and "Usage: " in shown.stdout
    bare = _run("baseline", cwd=tmp_path)
    assert bare.returncode == 2 and "covariance" in bare.stdout + bare.stderr


def test_a_missing_extra_names_the_extra_not_the_module() -> None:
    message = str(MissingExtraError("sklearn.base", "ml"))
    assert "sklearn" not in message
    assert message == "this feature needs the optional extra [ml]: pip install 'semantic3d[ml]'"


_WITHOUT = """
import sys
from importlib.abc import MetaPathFinder

class Absent(MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.partition(".")[0] in {absent!r}:
            raise ModuleNotFoundError(f"No module named {{name!r}}", name=name)
        return None

sys.meta_path.insert(0, Absent())
from semantic3d.cli.app import main
main()
"""


def test_a_command_without_its_extra_names_the_extra_in_one_line(tmp_path: Path) -> None:
    # scikit-learn and scipy missing, as after `pip install semantic3d`: the user reads
    # which extra to install, not which module (`'sklearn.base'`) failed to import.
    (tmp_path / "data").mkdir()
    result = subprocess.run(
        [
            *(sys.executable, "-c", _WITHOUT.format(absent=("sklearn", "scipy"))),
            *("baseline", "covariance", "train", "--data", "data", "--out", "m.s3d"),
        ],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=120,
        check=False,
    )
    assert result.returncode == 2
    line = _one_line(result)
    assert line == "error: this feature needs the optional extra [ml]: pip install 'semantic3d[ml]'"
    assert not (tmp_path / "m.s3d").exists()


def test_an_existing_output_names_the_flag_on_the_command_line(tmp_path: Path) -> None:
    from semantic3d.cli.console import _error_message

    paths = [tmp_path / "a.labels", tmp_path / "b.labels"]
    for path in paths:
        path.write_text("1\n")
    with pytest.raises(OutputExistsError) as caught:
        refuse_existing_paths(paths, overwrite=False)
    assert "overwrite=True" in str(caught.value)  # the library names its argument
    line = _error_message(caught.value)
    assert (
        line == f"{paths[0]}: already exists (and 1 other output); pass --overwrite to replace it"
    )
    refuse_existing_paths(paths, overwrite=True)


def test_other_libraries_log_only_with_verbose() -> None:
    def record(name: str, level: int) -> logging.LogRecord:
        return logging.LogRecord(name, level, __file__, 1, "message", None, None)

    assert not _this_package_or_critical(record("laspy.lasreader", logging.ERROR))
    assert not _this_package_or_critical(record("distributed.worker", logging.INFO))
    assert _this_package_or_critical(record("semantic3d.io.las", logging.WARNING))
    assert _this_package_or_critical(record("laspy", logging.CRITICAL))


def test_a_truncated_laz_file_is_one_line(tmp_path: Path) -> None:
    pytest.importorskip("laspy")
    pytest.importorskip("lazrs")
    import numpy as np

    from semantic3d.core.pointcloud import PointCloud
    from semantic3d.io.formats import write_points

    rng = np.random.default_rng(0)
    n = 20_000
    cloud = PointCloud(
        xyz=rng.uniform(0, 50, (n, 3)),
        intensity=rng.integers(0, 255, n, dtype=np.int32),
        rgb=rng.integers(0, 255, (n, 3), dtype=np.uint8),
    )
    whole = tmp_path / "whole.laz"
    write_points(whole, [cloud])
    cut = tmp_path / "cut.laz"
    cut.write_bytes(whole.read_bytes()[: whole.stat().st_size // 2])
    result = _run("info", str(cut), cwd=tmp_path)
    assert result.returncode == 2
    errors = [line for line in result.stderr.splitlines() if "error" in line.lower()]
    assert len(errors) == 1 and errors[0].startswith("error: ") and "cut.laz" in errors[0]
    assert "laspy" not in result.stderr
