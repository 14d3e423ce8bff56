from __future__ import annotations

import json
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given

from semantic3d.core import DataFormatError, PointCloud
from semantic3d.io.ascii import write_ascii_points
from semantic3d.io.cache import (
    CACHE_FORMAT_VERSION,
    SourceInfo,
    is_cache_current,
    iter_cache,
    open_cache,
    open_cache_writer,
    read_cache,
    write_cache,
)
from semantic3d.io.conversion import build_cache
from semantic3d.io.formats import read_points
from semantic3d.io.labels import write_labels
from tests.factories import ROUND_TRIP, clouds, random_cloud, split


def _entries(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir())


@given(cloud=clouds())
@ROUND_TRIP
def test_round_trip_is_exact(tmp_path_factory: pytest.TempPathFactory, cloud: PointCloud) -> None:
    path = tmp_path_factory.mktemp("cache") / "scan.cache"
    assert write_cache(path, split(cloud)) == cloud.n_points
    back = read_cache(path)
    assert back.equals(cloud)
    assert (back.labels is None) == (cloud.labels is None)


def test_chunks_have_the_asked_size_and_join_to_the_whole(tmp_path: Path) -> None:
    cloud = random_cloud(1000, seed=7)
    write_cache(tmp_path / "scan.cache", [cloud])
    chunks = list(iter_cache(tmp_path / "scan.cache", chunk_size=256))
    assert [c.n_points for c in chunks] == [256, 256, 256, 232]
    assert PointCloud.concatenate(chunks).equals(read_cache(tmp_path / "scan.cache"))
    chunks[0].xyz[0, 0] = 1e9  # chunks are in-memory copies, independent of the files
    assert read_cache(tmp_path / "scan.cache").equals(cloud)


def test_open_cache_maps_the_columns_without_reading(tmp_path: Path) -> None:
    cloud = random_cloud(500, seed=1, offset=870_000.0)
    path = tmp_path / "scan.cache"
    write_cache(path, [cloud])
    scan = open_cache(path)
    assert scan.n_points == 500
    assert isinstance(scan.xyz, np.memmap)  # a view of the file, not a copy
    assert not scan.xyz.flags.writeable
    assert scan.cloud[100:200].equals(cloud[100:200])
    assert _entries(path) == ["intensity.npy", "labels.npy", "meta.json", "rgb.npy", "xyz.npy"]
    # Plain numpy reads the columns: the cache is self-describing.
    assert np.array_equal(np.load(path / "xyz.npy"), cloud.xyz)
    assert np.load(path / "rgb.npy").shape == (500, 3)
    meta = json.loads((path / "meta.json").read_text())
    assert meta["n_points"] == 500 and meta["version"] == CACHE_FORMAT_VERSION
    assert meta["columns"]["intensity"] == {"file": "intensity.npy", "dtype": "<i4", "shape": [500]}


def test_unlabelled_cache_has_no_labels_column(tmp_path: Path) -> None:
    write_cache(tmp_path / "scan.cache", [random_cloud(5, labels=False)])
    assert "labels.npy" not in _entries(tmp_path / "scan.cache")
    assert open_cache(tmp_path / "scan.cache").labels is None


def test_failed_write_leaves_nothing_behind(tmp_path: Path) -> None:
    def chunks() -> Iterator[PointCloud]:
        yield random_cloud(10)
        raise RuntimeError("source broke")

    with pytest.raises(RuntimeError, match="source broke"):
        write_cache(tmp_path / "scan.cache", chunks())
    assert _entries(tmp_path) == []


def test_failed_rewrite_keeps_the_previous_cache(tmp_path: Path) -> None:
    path = tmp_path / "scan.cache"
    old = random_cloud(10, seed=1)
    write_cache(path, [old])
    with pytest.raises(DataFormatError, match="expected every chunk with labels"):
        write_cache(path, [random_cloud(3), random_cloud(3, labels=False)])
    assert read_cache(path).equals(old)
    assert _entries(tmp_path) == ["scan.cache"]


def test_rewrite_replaces_the_previous_cache(tmp_path: Path) -> None:
    path = tmp_path / "scan.cache"
    write_cache(path, [random_cloud(10, seed=1)])
    new = random_cloud(4, seed=2, labels=False)
    write_cache(path, [new])
    assert read_cache(path).equals(new)
    assert _entries(tmp_path) == ["scan.cache"]


def test_refuses_to_overwrite_something_that_is_not_a_cache(tmp_path: Path) -> None:
    folder = tmp_path / "photos"
    folder.mkdir()
    (folder / "holiday.jpg").write_bytes(b"...")
    with pytest.raises(DataFormatError, match=r"photos: expected a new path, an empty folder"):
        write_cache(folder, [random_cloud(3)])
    assert _entries(folder) == ["holiday.jpg"]


@pytest.fixture
def cache(tmp_path: Path) -> Path:
    path = tmp_path / "scan.cache"
    write_cache(path, [random_cloud(100)])
    return path


def test_missing_meta_is_reported(tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataFormatError, match=r"empty: expected a cache folder holding meta\.json"):
        open_cache(tmp_path / "empty")


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("{not json", r"meta\.json: expected JSON, found corrupt text"),
        (
            '{"format": "something-else"}',
            r"expected format 'semantic3d-cache', found 'something-else'",
        ),
        (
            '{"format": "semantic3d-cache", "version": 99}',
            r"expected cache format version 1, found 99",
        ),
        (
            '{"format": "semantic3d-cache", "version": 1, "n_points": -1, "has_labels": true}',
            r"expected a non-negative n_points",
        ),
    ],
)
def test_corrupt_meta_is_reported(cache: Path, text: str, message: str) -> None:
    (cache / "meta.json").write_text(text)
    with pytest.raises(DataFormatError, match=message):
        open_cache(cache)


def test_truncated_column_is_reported(cache: Path) -> None:
    column = cache / "xyz.npy"
    column.write_bytes(column.read_bytes()[:-8])
    with pytest.raises(
        DataFormatError, match=r"xyz\.npy: expected a \.npy column of shape \(100, 3\), .*truncated"
    ):
        open_cache(cache)


def test_column_with_extra_bytes_is_reported(cache: Path) -> None:
    with (cache / "intensity.npy").open("ab") as stream:
        stream.write(b"\x00" * 4)
    with pytest.raises(DataFormatError, match=r"intensity\.npy: expected 528 bytes, found 532"):
        open_cache(cache)


def test_column_disagreeing_with_meta_is_reported(cache: Path) -> None:
    np.save(cache / "rgb.npy", np.zeros((100, 3), np.int16))
    with pytest.raises(
        DataFormatError, match=r"rgb\.npy: expected shape \(100, 3\) uint8, found \(100, 3\) int16"
    ):
        open_cache(cache)
    (cache / "rgb.npy").unlink()
    with pytest.raises(DataFormatError, match=r"expected column file rgb\.npy, found none"):
        open_cache(cache)


def test_garbage_column_is_reported(cache: Path) -> None:
    (cache / "labels.npy").write_bytes(b"definitely not numpy")
    with pytest.raises(DataFormatError, match=r"labels\.npy: expected a \.npy column"):
        open_cache(cache)


def test_build_cache_converts_once_and_notices_changes(tmp_path: Path) -> None:
    cloud = random_cloud(3000, seed=12, offset=870_000.0)
    points, labels = tmp_path / "scan.txt", tmp_path / "scan.labels"
    write_ascii_points(points, [cloud], labels_path=labels)
    calls: list[tuple[int, int]] = []
    scan = build_cache(
        points,
        tmp_path / "scan.cache",
        labels_path=labels,
        chunk_size=1000,
        progress=lambda done, total: calls.append((done, total)),
    )
    assert scan.cloud.equals(cloud)
    assert [done for done, _ in calls] == [1000, 2000, 3000, 3000]
    assert calls[-1] == (3000, 3000)
    assert scan.meta.source == SourceInfo.of(points)
    assert scan.meta.labels_source == SourceInfo.of(labels)
    assert is_cache_current(tmp_path / "scan.cache", points, labels_path=labels)
    assert not is_cache_current(tmp_path / "scan.cache", points)  # other labels (none)

    meta_written = (tmp_path / "scan.cache" / "meta.json").stat().st_mtime_ns
    build_cache(points, tmp_path / "scan.cache", labels_path=labels)  # current: reused
    assert (tmp_path / "scan.cache" / "meta.json").stat().st_mtime_ns == meta_written

    write_labels(labels, [np.full(3000, 4, np.uint8)])
    os.utime(labels, ns=(meta_written + 10**9, meta_written + 10**9))
    assert not is_cache_current(tmp_path / "scan.cache", points, labels_path=labels)
    rebuilt = build_cache(points, tmp_path / "scan.cache", labels_path=labels)
    assert rebuilt.labels is not None and set(np.unique(rebuilt.labels)) == {4}


def test_build_cache_from_a_real_sample(shared_data: Path, tmp_path: Path) -> None:
    folder = shared_data / "odm-brighton"
    points = folder / "brighton_small.txt"
    if not points.is_file():
        pytest.skip("brighton sample not available")
    scan = build_cache(points, tmp_path / "b.cache", labels_path=folder / "brighton_small.labels")
    assert scan.cloud.equals(read_points(points))
    assert scan.n_points == 401_286
    assert open_cache(tmp_path / "b.cache").meta.source == SourceInfo.of(points)


def test_writer_counts_and_is_atomic_until_closed(tmp_path: Path) -> None:
    path = tmp_path / "scan.cache"
    with open_cache_writer(path) as writer:
        writer.write(random_cloud(3, seed=1))
        writer.write(random_cloud(2, seed=2))
        assert not path.exists()  # only the hidden staging folder exists so far
    assert writer.n_points == 5
    assert open_cache(path).n_points == 5
    assert _entries(tmp_path) == ["scan.cache"]
