"""``Semantic3D(root)``: presence, sizes, missing scans and paths per split."""

from __future__ import annotations

from pathlib import Path

import pytest

from semantic3d.datasets.registry import Split, UnknownScanError, scan, scans
from semantic3d.datasets.semantic3d import Semantic3D


def test_empty_folder_misses_everything(tmp_path: Path) -> None:
    dataset = Semantic3D(tmp_path)

    assert dataset.missing() == scans()
    assert dataset.present() == ()
    assert not dataset.is_complete("train")
    assert all(files.size_bytes == 0 for files in dataset.scans())


def test_paths_of_a_training_scan(tmp_path: Path) -> None:
    files = Semantic3D(tmp_path).paths("neugasse_station1")

    assert files.points_path == tmp_path / "neugasse_station1_xyz_intensity_rgb.txt"
    assert files.labels_path == tmp_path / "neugasse_station1_xyz_intensity_rgb.labels"
    assert not files.has_points and not files.has_labels and not files.complete


def test_test_scans_have_no_labels_path(tmp_path: Path) -> None:
    files = Semantic3D(tmp_path).paths("sg27_station10_reduced")

    assert files.points_path == tmp_path / "sg27_station10_rgb_intensity-reduced.txt"
    assert files.labels_path is None


def test_presence_and_sizes_follow_the_disk(tmp_path: Path) -> None:
    dataset = Semantic3D(tmp_path)
    train = scan("bildstein_station3")
    (tmp_path / train.points.filename).write_bytes(b"x" * 70)
    test = scan("birdfountain_station1")
    (tmp_path / test.points.filename).write_bytes(b"y" * 30)

    files = dataset.paths(train.name)
    assert (files.points_bytes, files.labels_bytes) == (70, None)
    assert not files.complete  # the ground truth is still missing
    assert dataset.present() == (dataset.paths(test.name),)
    assert dataset.paths(test.name).size_bytes == 30

    assert train.labels is not None
    (tmp_path / train.labels.filename).write_bytes(b"1\n" * 5)
    files = dataset.paths(train.name)
    assert files.complete and files.size_bytes == 80
    assert [f.scan.name for f in dataset.present(Split.TRAIN)] == [train.name]
    assert len(dataset.missing(Split.TRAIN)) == 14
    assert len(dataset.missing(Split.SEMANTIC_8)) == 14


def test_a_split_is_complete_once_every_file_is_there(tmp_path: Path) -> None:
    for info in scans("reduced-8"):
        (tmp_path / info.points.filename).write_text("0 0 0 0 0 0 0\n")

    dataset = Semantic3D(tmp_path)
    assert dataset.is_complete("reduced-8")
    assert not dataset.is_complete()
    assert len(dataset.scans("reduced-8")) == 4


def test_a_folder_under_a_file_name_does_not_count(tmp_path: Path) -> None:
    info = scan("sg28_station2_reduced")
    (tmp_path / info.points.filename).mkdir()

    assert not Semantic3D(tmp_path).paths(info.name).has_points


def test_unknown_scan_name(tmp_path: Path) -> None:
    with pytest.raises(UnknownScanError, match="found 'station1_xyz_intensity_rgb'"):
        Semantic3D(tmp_path).paths("station1_xyz_intensity_rgb")
