from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import example, given

from semantic3d.core import DataFormatError, PointCloud
from semantic3d.io.ascii import read_ascii_points, write_ascii_points
from semantic3d.io.formats import (
    PointFormat,
    describe_columns,
    detect_format,
    estimate_point_count,
    iter_points,
    read_points,
    sibling_labels_path,
    summarize_points,
    write_points,
)
from semantic3d.io.labels import write_labels
from tests.factories import ROUND_TRIP, clouds, random_cloud, split


@pytest.mark.parametrize(
    ("name", "expected"),
    [
        ("scan.txt", PointFormat.ASCII),
        ("scan.xyz", PointFormat.ASCII),
        ("SCAN.TXT", PointFormat.ASCII),
        ("scan.las", PointFormat.LAS),
        ("scan.LAZ", PointFormat.LAZ),
        ("scan.ply", PointFormat.PLY),
        ("scan.cache", PointFormat.CACHE),
    ],
)
def test_detect_format_by_suffix(name: str, expected: PointFormat) -> None:
    assert detect_format(name) is expected


def test_detect_format_takes_any_folder_as_cache(tmp_path: Path) -> None:
    folder = tmp_path / "no_suffix"
    folder.mkdir()
    assert detect_format(folder) is PointFormat.CACHE


@pytest.mark.parametrize("name", ["scan.csv", "scan", "scan.labels", "scan.las.gz"])
def test_detect_format_rejects_unknown_suffixes(name: str) -> None:
    with pytest.raises(DataFormatError, match=r"expected a point file ending in one of .*found"):
        detect_format(name)


def test_sibling_labels_path(tmp_path: Path) -> None:
    points = tmp_path / "scan.txt"
    assert sibling_labels_path(points) is None
    (tmp_path / "scan.labels").write_text("1\n")
    assert sibling_labels_path(points) == tmp_path / "scan.labels"


SUFFIXES = [".txt", ".las", ".laz", ".ply", ".cache"]


EDGE_CLOUDS = [
    PointCloud.empty(),
    PointCloud.empty(with_labels=True),
    PointCloud.from_arrays(  # one georeferenced point, negative intensity, the last class
        [[870_277.390, 6_617_096.360, 180.060]], intensity=[-1515], rgb=[[0, 128, 255]], labels=[8]
    ),
]


@pytest.mark.parametrize("suffix", SUFFIXES)
@given(cloud=clouds(millimetres=True))
@example(cloud=EDGE_CLOUDS[0])
@example(cloud=EDGE_CLOUDS[1])
@example(cloud=EDGE_CLOUDS[2])
@ROUND_TRIP
def test_write_then_read_round_trips_every_format(
    tmp_path_factory: pytest.TempPathFactory, suffix: str, cloud: PointCloud
) -> None:
    path = tmp_path_factory.mktemp("rt") / f"scan{suffix}"
    assert write_points(path, split(cloud)) == cloud.n_points
    back = read_points(path)
    assert np.abs(back.xyz - cloud.xyz).max(initial=0.0) < 1e-6  # millimetres exact
    assert np.array_equal(back.intensity, cloud.intensity)
    assert np.array_equal(back.rgb, cloud.rgb)
    if cloud.n_points:  # an empty ASCII file has nowhere to say it had labels
        assert (back.labels is None) == (cloud.labels is None)
    if cloud.labels is not None and cloud.n_points:
        assert np.array_equal(back.labels, cloud.labels)


@pytest.mark.parametrize("suffix", SUFFIXES)
def test_chunked_reading_equals_whole_file_for_every_format(tmp_path: Path, suffix: str) -> None:
    cloud = random_cloud(1000, seed=3, offset=870_000.0)
    path = tmp_path / f"scan{suffix}"
    write_points(path, [cloud])
    chunks = list(iter_points(path, chunk_size=300))
    assert [c.n_points for c in chunks] == [300, 300, 300, 100]
    assert PointCloud.concatenate(chunks).equals(read_points(path))
    assert read_points(path).equals(cloud)


def test_conversion_chain_through_every_format_keeps_everything(tmp_path: Path) -> None:
    cloud = random_cloud(2000, seed=5, offset=870_000.0)
    path = tmp_path / "start.txt"
    write_points(path, [cloud])
    for step, suffix in enumerate([".laz", ".ply", ".cache", ".las", ".xyz"]):
        target = tmp_path / f"step{step}{suffix}"
        write_points(target, iter_points(path, chunk_size=333))
        path = target
    assert read_points(path).equals(cloud)


def test_ascii_labels_go_to_and_come_from_the_sibling_file(tmp_path: Path) -> None:
    cloud = random_cloud(50, seed=1)
    write_points(tmp_path / "scan.txt", [cloud])
    assert (tmp_path / "scan.labels").is_file()
    assert read_points(tmp_path / "scan.txt").equals(cloud)
    assert read_ascii_points(tmp_path / "scan.txt").labels is None  # plain reader: points only


def test_ascii_labels_path_overrides_the_sibling(tmp_path: Path) -> None:
    cloud = random_cloud(50, seed=1)
    write_points(tmp_path / "scan.txt", [cloud], labels_path=tmp_path / "other.labels")
    assert not (tmp_path / "scan.labels").exists()
    back = read_points(tmp_path / "scan.txt", labels_path=tmp_path / "other.labels")
    assert back.equals(cloud)


@pytest.mark.parametrize("suffix", [".las", ".ply", ".cache"])
def test_external_labels_override_embedded_ones(tmp_path: Path, suffix: str) -> None:
    cloud = random_cloud(700, seed=2)
    path = tmp_path / f"scan{suffix}"
    write_points(path, [cloud])
    other = (cloud.labels + 1) % 9
    write_labels(tmp_path / "other.labels", [other])
    back = list(iter_points(path, chunk_size=256, labels_path=tmp_path / "other.labels"))
    assert np.array_equal(np.concatenate([c.labels for c in back]), other)


@pytest.mark.parametrize("n_labels", [699, 701])
def test_external_labels_of_another_length_are_rejected(tmp_path: Path, n_labels: int) -> None:
    path = tmp_path / "scan.ply"
    write_points(path, [random_cloud(700)])
    write_labels(tmp_path / "bad.labels", [np.ones(n_labels, np.uint8)])
    with pytest.raises(DataFormatError, match=r"bad\.labels: expected one label per point"):
        read_points(path, labels_path=tmp_path / "bad.labels")


def test_labels_path_is_rejected_for_formats_that_embed_labels(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="labels_path applies to ASCII output only"):
        write_points(tmp_path / "scan.las", [random_cloud(5)], labels_path=tmp_path / "x.labels")


def test_writing_unlabelled_ascii_beside_a_stale_labels_file_warns(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    (tmp_path / "scan.labels").write_text("1\n")
    write_points(tmp_path / "scan.txt", [random_cloud(3, labels=False)])
    assert "will be read as its labels" in caplog.text


def test_estimate_point_count_is_exact_from_headers(tmp_path: Path) -> None:
    cloud = random_cloud(1234, seed=4)
    for suffix in [".las", ".laz", ".ply", ".cache", ".txt"]:
        path = tmp_path / f"scan{suffix}"
        write_points(path, [cloud])
        estimate = estimate_point_count(path)
        assert (estimate.n_points, estimate.exact) == (1234, True), suffix


def test_estimate_point_count_extrapolates_large_ascii_files(tmp_path: Path) -> None:
    path = tmp_path / "big.txt"
    write_ascii_points(path, [random_cloud(60_000, seed=6, labels=False)])
    assert path.stat().st_size > 1 << 21
    estimate = estimate_point_count(path)
    assert not estimate.exact
    assert abs(estimate.n_points - 60_000) < 0.05 * 60_000


def test_summarize_points_matches_the_arrays(tmp_path: Path) -> None:
    cloud = random_cloud(5000, seed=8, offset=870_000.0)
    path = tmp_path / "scan.laz"
    write_points(path, [cloud])
    seen: list[int] = []
    summary = summarize_points(path, chunk_size=1000, progress=seen.append)
    assert seen == [1000, 2000, 3000, 4000, 5000]
    assert summary.format is PointFormat.LAZ
    assert summary.n_points == 5000
    assert summary.min_xyz is not None and summary.max_xyz is not None
    assert np.allclose(summary.min_xyz, cloud.xyz.min(axis=0), atol=1e-9)
    assert np.allclose(summary.max_xyz, cloud.xyz.max(axis=0), atol=1e-9)
    assert summary.intensity_range == (cloud.intensity.min(), cloud.intensity.max())
    assert summary.label_counts is not None and cloud.labels is not None
    assert np.array_equal(summary.label_counts[:9], np.bincount(cloud.labels, minlength=9))
    assert "label uint8" in summary.columns


def test_summarize_points_of_an_empty_unlabelled_file(tmp_path: Path) -> None:
    path = tmp_path / "empty.ply"
    write_points(path, [])
    summary = summarize_points(path)
    assert summary.n_points == 0
    assert summary.min_xyz is None and summary.intensity_range is None
    assert summary.label_counts is None


def test_describe_columns_for_each_format(tmp_path: Path) -> None:
    cloud = random_cloud(5)
    for suffix in SUFFIXES:
        write_points(tmp_path / f"scan{suffix}", [cloud])
    assert describe_columns(tmp_path / "scan.txt")[-1] == "label text (in scan.labels)"
    assert describe_columns(tmp_path / "scan.ply")[-1] == "scalar_label uchar"
    assert describe_columns(tmp_path / "scan.cache")[0] == "xyz float64 (5, 3)"
    las_columns = describe_columns(tmp_path / "scan.las")
    assert {"semantic3d_intensity int32", "label uint8", "red uint16"} <= set(las_columns)


SAMPLES = [
    "ign-lidarhd-toy/870000_6618000_subset.txt",
    "oakland/oakland_part2_ac.txt",
    "odm-brighton/brighton_small.txt",
]


@pytest.mark.parametrize("sample", SAMPLES)
def test_real_samples_survive_every_format(shared_data: Path, tmp_path: Path, sample: str) -> None:
    source = shared_data / sample
    if not source.is_file():
        pytest.skip(f"{sample} is not available")
    original = read_points(source)
    assert original.labels is not None  # from the sibling .labels
    for suffix in [".las", ".laz", ".ply", ".cache", ".txt"]:
        target = tmp_path / f"copy{suffix}"
        write_points(target, iter_points(source, chunk_size=50_000))
        back = read_points(target)
        # Millimetres survive, even at x ≈ 870 000 m: equal after rounding to the mm.
        assert np.array_equal(np.round(back.xyz * 1000), np.round(original.xyz * 1000)), suffix
        assert np.abs(back.xyz - original.xyz).max() < 1e-6, suffix
        assert back.intensity.tolist() == original.intensity.tolist(), suffix
        assert np.array_equal(back.rgb, original.rgb), suffix
        assert np.array_equal(back.labels, original.labels), suffix


def test_real_sample_files_are_read_whole_and_chunked_alike(shared_data: Path) -> None:
    source = shared_data / SAMPLES[0]
    if not source.is_file():
        pytest.skip("IGN sample not available")
    whole = read_points(source)
    chunks = list(iter_points(source, chunk_size=10_000))
    assert PointCloud.concatenate(chunks).equals(whole)
    assert whole.xyz[:, 0].min() > 869_000  # the georeferenced one


def test_missing_file_is_a_plain_os_error(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError):
        list(iter_points(tmp_path / "absent.las"))
