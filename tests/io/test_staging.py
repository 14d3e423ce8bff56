"""Writers never leave a half-written file under the final name (errors and Ctrl-C alike)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from semantic3d.core import DataFormatError, PointCloud
from semantic3d.io.formats import read_points, write_points
from semantic3d.io.labels import read_labels, write_labels
from semantic3d.io.staging import StagedPath
from tests.factories import random_cloud

OUTPUTS = ["out.txt", "out.las", "out.laz", "out.ply", "out.cache"]


def _interrupted(exc: BaseException) -> Iterator[PointCloud]:
    yield random_cloud(500, seed=1)
    yield random_cloud(500, seed=2)
    raise exc


@pytest.mark.parametrize("name", OUTPUTS)
@pytest.mark.parametrize("exc", [KeyboardInterrupt(), RuntimeError("source broke")])
def test_interrupted_write_keeps_the_previous_file_and_leaves_no_temporary(
    tmp_path: Path, name: str, exc: BaseException
) -> None:
    destination = tmp_path / name
    previous = random_cloud(30, seed=9)
    write_points(destination, [previous])
    before = sorted(p.name for p in tmp_path.iterdir())
    with pytest.raises(type(exc)):
        write_points(destination, _interrupted(exc))
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # no .partial files
    assert read_points(destination).equals(previous)


@pytest.mark.parametrize("name", OUTPUTS)
def test_interrupted_first_write_leaves_nothing(tmp_path: Path, name: str) -> None:
    with pytest.raises(KeyboardInterrupt):
        write_points(tmp_path / name, _interrupted(KeyboardInterrupt()))
    assert list(tmp_path.iterdir()) == []


def test_bad_chunk_midway_leaves_nothing(tmp_path: Path) -> None:
    chunks = [random_cloud(10, seed=1), random_cloud(10, seed=2, labels=False)]
    with pytest.raises(DataFormatError, match=r"out\.las: expected every chunk with labels"):
        write_points(tmp_path / "out.las", chunks)  # the message names the final file
    assert list(tmp_path.iterdir()) == []


def test_interrupted_labels_write_keeps_the_previous_file(tmp_path: Path) -> None:
    path = tmp_path / "scan.labels"
    write_labels(path, [np.array([1, 2, 3], np.uint8)])

    def chunks() -> Iterator[np.ndarray]:
        yield np.array([4, 5], np.uint8)
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        write_labels(path, chunks())
    assert [p.name for p in tmp_path.iterdir()] == ["scan.labels"]
    assert read_labels(path).tolist() == [1, 2, 3]


def test_staged_path_keeps_folder_and_suffix(tmp_path: Path) -> None:
    staged = StagedPath(tmp_path / "scan.labels")
    assert staged.temp.parent == tmp_path and staged.temp.suffix == ".labels"
    assert staged.temp != StagedPath(tmp_path / "scan.labels").temp  # unique per writer
    staged.temp.write_bytes(b"1\n")
    staged.commit()
    assert (tmp_path / "scan.labels").read_bytes() == b"1\n" and not staged.temp.exists()
    staged.discard()  # nothing left to remove: no error
