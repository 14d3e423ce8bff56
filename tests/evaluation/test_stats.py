"""Class statistics: points per class per split."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from semantic3d.core.errors import DataFormatError
from semantic3d.evaluation.stats import (
    class_table,
    compute_class_statistics,
    count_label_values,
    split_of,
)
from tests.evaluation.conftest import labels_bytes


def test_counts_per_split_use_registry_names(tmp_path: Path) -> None:
    (tmp_path / "bildstein_station1_xyz_intensity_rgb.labels").write_bytes(
        labels_bytes([0, 1, 1, 8])
    )
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "sg27_station1_intensity_rgb.labels").write_bytes(labels_bytes([3, 3]))
    (tmp_path / "my_scan.labels").write_bytes(labels_bytes([5, 0, 0]))
    (tmp_path / "._my_scan.labels").write_bytes(b"\x00\x05\x16\x07 macOS metadata")
    calls: list[tuple[int, int]] = []
    statistics = compute_class_statistics(
        tmp_path, progress=lambda done, total: calls.append((done, total))
    )
    assert statistics.splits == ("train", "custom")
    by_split = statistics.counts_by_split()
    np.testing.assert_array_equal(by_split["train"], [1, 2, 0, 2, 0, 0, 0, 0, 1])
    np.testing.assert_array_equal(by_split["custom"], [2, 0, 0, 0, 0, 1, 0, 0, 0])
    np.testing.assert_array_equal(
        statistics.class_counts_by_split()["train"], [2, 0, 2, 0, 0, 0, 0, 1]
    )
    assert calls[-1][0] == calls[-1][1]
    header, rows = class_table(statistics)
    assert header[:3] == ["Split", "Scans", "unlabelled"]
    assert rows[0] == ["train", "2", "1", "2", "0", "2", "0", "0", "0", "0", "1", "6"]


def test_split_overrides_and_lookup(tmp_path: Path) -> None:
    (tmp_path / "x.labels").write_bytes(labels_bytes([1]))
    statistics = compute_class_statistics(tmp_path, splits={"x": "validation"})
    assert statistics.splits == ("validation",)
    assert split_of("sg28_station4") == "train"
    assert split_of("sg28_Station2_rgb_intensity-reduced") == "reduced-8"
    assert split_of("elsewhere") == "custom"


def test_counts_match_numpy_on_a_real_scan(shared_data: Path) -> None:
    path = shared_data / "odm-brighton" / "brighton_small.labels"
    values = np.loadtxt(path, dtype=np.int64)
    np.testing.assert_array_equal(count_label_values(path), np.bincount(values, minlength=9))


def test_bad_folders_and_values(tmp_path: Path) -> None:
    with pytest.raises(DataFormatError, match="expected at least one"):
        compute_class_statistics(tmp_path)
    (tmp_path / "bad.labels").write_bytes(b"1\n9\n")
    with pytest.raises(DataFormatError, match=r"bad.labels: expected label values 0..8, found 9"):
        compute_class_statistics(tmp_path)
