from __future__ import annotations

import numpy as np
import pytest

from semantic3d.core import PointCloud, ShapeError
from tests.factories import random_cloud


def test_from_arrays_converts_dtypes_and_fills_missing_columns() -> None:
    cloud = PointCloud.from_arrays([[1, 2, 3], [4, 5, 6]])
    assert cloud.xyz.dtype == np.float64
    assert cloud.intensity.dtype == np.int32 and not cloud.intensity.any()
    assert cloud.rgb.shape == (2, 3) and cloud.rgb.dtype == np.uint8
    assert cloud.labels is None
    assert len(cloud) == cloud.n_points == 2


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"xyz": np.zeros((3, 2))}, r"xyz: expected an \(n, 3\) float64 array, found \(3, 2\)"),
        ({"intensity": np.zeros(2, np.int32)}, r"intensity: expected \(3,\) int32, found \(2,\)"),
        (
            {"rgb": np.zeros((3, 3), np.int64)},
            r"rgb: expected \(3, 3\) uint8, found \(3, 3\) int64",
        ),
        ({"labels": np.zeros(4, np.uint8)}, r"labels: expected \(3,\) uint8, found \(4,\)"),
    ],
)
def test_wrong_shapes_and_dtypes_are_rejected(kwargs: dict, message: str) -> None:
    arrays = {
        "xyz": np.zeros((3, 3)),
        "intensity": np.zeros(3, np.int32),
        "rgb": np.zeros((3, 3), np.uint8),
        "labels": None,
    }
    arrays.update(kwargs)
    with pytest.raises(ShapeError, match=message):
        PointCloud(**arrays)


def test_slicing_masking_and_concatenation() -> None:
    cloud = random_cloud(100)
    assert cloud[10:20].n_points == 10
    mask = cloud.labels == 3
    part = cloud[mask]
    assert (part.labels == 3).all()
    joined = PointCloud.concatenate([cloud[:40], cloud[40:]])
    assert joined.equals(cloud)
    unlabelled = PointCloud.concatenate([cloud[:5], cloud[5:].with_labels(None)])
    assert unlabelled.labels is None


def test_bounds_and_empty() -> None:
    cloud = PointCloud.from_arrays([[0, 5, -1], [2, 3, 4]])
    low, high = cloud.bounds()
    assert low.tolist() == [0, 3, -1] and high.tolist() == [2, 5, 4]
    with pytest.raises(ShapeError, match="empty"):
        PointCloud.empty().bounds()
    assert PointCloud.concatenate([]).n_points == 0


def test_equals_compares_labels() -> None:
    cloud = random_cloud(10)
    assert not cloud.equals(cloud.with_labels(None))
    other = cloud.with_labels(np.zeros(10, np.uint8))
    assert not cloud.equals(other) or (cloud.labels == 0).all()
