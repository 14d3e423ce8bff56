"""A ``.labels`` file that does not fit the scan is refused before anything is written."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from semantic3d.cli.app import app
from semantic3d.labelling.errors import LabelFileError
from semantic3d.labelling.labelfile import read_label_file
from semantic3d.labelling.opening import open_label_session

from .conftest import NODE_CAPACITY


def _bad_files(tmp_path: Path, n: int) -> list[tuple[Path, str]]:
    short = tmp_path / "short.labels"
    short.write_text("1\n" * (n - 3))
    long = tmp_path / "long.labels"
    long.write_text("1\n" * (n + 2))
    high = tmp_path / "high.labels"
    high.write_text("1\n" * 10 + "9\n" + "1\n" * (n - 11))
    text = tmp_path / "text.labels"
    text.write_text("1\n" * 5 + "car\n" + "1\n" * (n - 6))
    return [
        (short, f"expected {n} labels .one per point of the scan., found {n - 3}"),
        (long, f"expected {n} labels .one per point of the scan., found {n + 2}"),
        (high, "line 11: expected label values 0..8, found 9"),
        (text, "line 6: expected one non-negative integer label, found 'car'"),
    ]


def test_bad_labels_files_are_refused_and_nothing_is_written(simulated_scan, tmp_path) -> None:
    n = simulated_scan.cache.n_points
    for path, message in _bad_files(tmp_path, n):
        before = path.read_bytes()
        with pytest.raises(LabelFileError, match=message):
            read_label_file(path, n_points=n)
        with pytest.raises(LabelFileError, match=message):
            open_label_session(
                simulated_scan.cache.path,
                labels_path=tmp_path / "out.labels",
                start_from=path,
                node_capacity=NODE_CAPACITY,
            )
        with pytest.raises(LabelFileError, match=message):
            open_label_session(
                simulated_scan.cache.path,
                labels_path=path,
                overwrite=True,
                node_capacity=NODE_CAPACITY,
            )
        assert path.read_bytes() == before
        assert not Path(f"{path}.journal").exists()
        assert not (tmp_path / "out.labels").exists()
        assert not (tmp_path / "out.labels.journal").exists()
    good = tmp_path / "good.labels"
    good.write_text("".join(f"{v}\n" for v in np.arange(n) % 9))
    np.testing.assert_array_equal(read_label_file(good, n_points=n), np.arange(n) % 9)


def test_cli_refuses_a_bad_labels_file_with_one_line(simulated_scan, tmp_path) -> None:
    n = simulated_scan.cache.n_points
    path, _ = _bad_files(tmp_path, n)[2]
    out = tmp_path / "out.labels"
    for command in (
        ["label", str(simulated_scan.cache.path), "--from", str(path), "--labels", str(out)],
        ["view", str(simulated_scan.cache.path), "--pred", str(path)],
    ):
        result = CliRunner().invoke(app, command)
        assert result.exit_code == 2, result.output
        assert "expected label values 0..8, found 9" in result.output
        assert "Traceback" not in result.output
