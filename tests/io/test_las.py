from __future__ import annotations

from pathlib import Path

import laspy
import numpy as np
import pytest
from hypothesis import given

from semantic3d.core import DataFormatError, PointCloud
from semantic3d.io.formats import write_points
from semantic3d.io.las import (
    ASPRS_BY_LABEL,
    INTENSITY_DIMENSION,
    INTENSITY_OFFSET,
    LABEL_BY_ASPRS,
    LABEL_DIMENSION,
    CrsError,
    iter_las,
    open_las_writer,
    read_las,
    write_las,
)
from tests.factories import ROUND_TRIP, clouds, random_cloud, split

SUFFIXES = [".las", ".laz"]


def _foreign_las(
    path: Path,
    *,
    classification: np.ndarray,
    intensity: np.ndarray,
    rgb16: np.ndarray | None,
    point_format: int = 3,
) -> np.ndarray:
    """A file as other software writes it (plain laspy, no extra dimensions); its xyz."""
    n = classification.size
    header = laspy.LasHeader(point_format=point_format, version="1.2")
    header.scales = np.full(3, 0.01)
    header.offsets = np.array([870_000.0, 6_617_000.0, 0.0])
    las = laspy.LasData(header)
    xyz = np.round(np.array([870_100.0, 6_617_100.0, 50.0]) + np.arange(n)[:, None] * 0.5, 2)
    las.x, las.y, las.z = xyz.T
    las.classification = classification
    las.intensity = intensity
    if rgb16 is not None:
        las.red, las.green, las.blue = rgb16.T
    las.write(path)
    return xyz


@pytest.mark.parametrize("suffix", SUFFIXES)
@given(cloud=clouds())
@ROUND_TRIP
def test_round_trip_keeps_millimetres_and_exact_values(
    tmp_path_factory: pytest.TempPathFactory, suffix: str, cloud: PointCloud
) -> None:
    path = tmp_path_factory.mktemp("las") / f"scan{suffix}"
    assert write_las(path, split(cloud)) == cloud.n_points
    back = read_las(path)
    assert back.n_points == cloud.n_points
    # Stored as int32 millimetres: within half a millimetre, whatever the float.
    assert np.abs(back.xyz - cloud.xyz).max(initial=0.0) <= 0.0005 + 1e-9
    assert np.array_equal(back.intensity, cloud.intensity)  # full int32 range, signed
    assert np.array_equal(back.rgb, cloud.rgb)
    assert (back.labels is None) == (cloud.labels is None)
    if cloud.labels is not None:
        assert np.array_equal(back.labels, cloud.labels)


@pytest.mark.parametrize("suffix", SUFFIXES)
@given(cloud=clouds(millimetres=True))
@ROUND_TRIP
def test_georeferenced_millimetres_come_back_exactly(
    tmp_path_factory: pytest.TempPathFactory, suffix: str, cloud: PointCloud
) -> None:
    path = tmp_path_factory.mktemp("las") / f"scan{suffix}"
    write_las(path, [cloud])
    back = read_las(path)
    assert np.array_equal(np.round(back.xyz * 1000), np.round(cloud.xyz * 1000))
    assert np.abs(back.xyz - cloud.xyz).max(initial=0.0) < 1e-6


@pytest.mark.parametrize("suffix", SUFFIXES)
def test_chunks_have_the_asked_size_and_join_to_the_whole(tmp_path: Path, suffix: str) -> None:
    cloud = random_cloud(2500, seed=11, offset=870_000.0)
    path = tmp_path / f"scan{suffix}"
    write_las(path, [cloud[:1000], cloud[1000:]])
    chunks = list(iter_las(path, chunk_size=1024))
    assert [c.n_points for c in chunks] == [1024, 1024, 452]
    assert PointCloud.concatenate(chunks).equals(read_las(path))
    assert read_las(path).equals(cloud)


def test_standard_fields_make_sense_to_other_software(tmp_path: Path) -> None:
    cloud = PointCloud.from_arrays(
        [[870_277.390, 6_617_096.360, 180.060], [870_300.5, 6_617_100.0, 181.0]] * 5,
        intensity=[-1515, 2047, -2048, 0, 70_000, -70_000, 1, 2, 3, 4],
        rgb=[[0, 128, 255]] * 10,
        labels=[0, 1, 2, 3, 4, 5, 6, 7, 8, 8],
    )
    path = tmp_path / "scan.las"
    write_las(path, [cloud])
    las = laspy.read(path)  # the plain laspy view
    assert las.header.version == laspy.header.Version(1, 4)
    assert las.header.point_format.id == 7
    assert np.allclose(las.header.scales, 0.001)
    assert las.header.offsets.tolist() == [870_277.0, 6_617_096.0, 180.0]  # floor of the minimum
    assert las.header.point_count == 10
    assert las.classification.tolist() == [1, 11, 2, 5, 3, 6, 64, 7, 65, 65]
    assert las.intensity.tolist() == [533, 4095, 0, 2048, 65535, 0, 2049, 2050, 2051, 2052]
    assert las[INTENSITY_DIMENSION].tolist() == cloud.intensity.tolist()
    assert las[LABEL_DIMENSION].tolist() == cloud.labels.tolist()
    assert las.red.tolist() == [0] * 10 and las.blue.tolist() == [65535] * 10
    assert las.green.tolist() == [128 * 257] * 10
    assert las.X[0] == 390 and las.Y[0] == 360 and las.Z[0] == 60  # whole millimetres
    assert las.return_number.min() == 1 and las.number_of_returns.min() == 1


def test_unlabelled_points_read_back_without_labels(tmp_path: Path) -> None:
    cloud = random_cloud(20, labels=False)
    write_las(tmp_path / "scan.laz", [cloud])
    assert LABEL_DIMENSION not in laspy.read(tmp_path / "scan.laz").point_format.dimension_names
    assert read_las(tmp_path / "scan.laz").labels is None
    assert read_las(tmp_path / "scan.laz").equals(cloud)


def test_asprs_tables_invert_each_other_on_standard_codes() -> None:
    for label in range(9):
        code = int(ASPRS_BY_LABEL[label])
        if code < 64 and label != 0:  # user-definable codes have no meaning elsewhere
            assert LABEL_BY_ASPRS[code] == label, (label, code)
    assert LABEL_BY_ASPRS[1] == 0 and LABEL_BY_ASPRS[64] == 0 and LABEL_BY_ASPRS[65] == 0


def test_foreign_file_maps_classes_and_keeps_raw_intensity(tmp_path: Path) -> None:
    codes = np.array([0, 1, 2, 3, 4, 5, 6, 7, 9, 11, 17, 18], dtype=np.uint8)
    rgb16 = np.array([[65535, 256, 0]] * codes.size, dtype=np.uint16)
    intensity = np.arange(codes.size, dtype=np.uint16) * 5000
    xyz = _foreign_las(
        tmp_path / "foreign.las", classification=codes, intensity=intensity, rgb16=rgb16
    )
    cloud = read_las(tmp_path / "foreign.las")
    assert cloud.labels is not None
    assert cloud.labels.tolist() == [0, 0, 2, 4, 4, 3, 5, 7, 0, 1, 0, 7]
    assert cloud.intensity.tolist() == intensity.tolist()
    assert cloud.rgb.tolist() == [[255, 1, 0]] * codes.size  # 16-bit colour >> 8
    assert np.abs(cloud.xyz - xyz).max() < 1e-6
    assert read_las(tmp_path / "foreign.las", map_classification=False).labels is None


def test_foreign_eight_bit_colours_are_read_unshifted(tmp_path: Path) -> None:
    rgb = np.array([[0, 0, 0], [10, 200, 255], [255, 255, 255]], dtype=np.uint16)
    _foreign_las(
        tmp_path / "eight.las",
        classification=np.zeros(3, np.uint8),
        intensity=np.zeros(3, np.uint16),
        rgb16=rgb,
    )
    assert read_las(tmp_path / "eight.las").rgb.tolist() == rgb.tolist()


def test_foreign_file_without_colour_reads_zeros(tmp_path: Path) -> None:
    _foreign_las(
        tmp_path / "plain.las",
        classification=np.full(4, 6, np.uint8),
        intensity=np.ones(4, np.uint16),
        rgb16=None,
        point_format=1,
    )
    cloud = read_las(tmp_path / "plain.las")
    assert cloud.rgb.tolist() == [[0, 0, 0]] * 4
    assert cloud.labels is not None and cloud.labels.tolist() == [5] * 4


def test_points_too_far_from_the_first_chunk_are_rejected(tmp_path: Path) -> None:
    near = random_cloud(10)
    far = PointCloud.from_arrays([[3_000_000.0, 0.0, 0.0]], labels=[1])
    path = tmp_path / "far.las"
    with pytest.raises(DataFormatError, match=r"far\.las: point #10 .*within ±2\^31 mm"):
        write_las(path, [near, far])
    assert not path.exists()  # no half-written file is left behind


def test_non_finite_coordinates_are_rejected(tmp_path: Path) -> None:
    bad = PointCloud.from_arrays([[0.0, 0.0, 0.0], [np.nan, 0.0, 0.0]])
    with pytest.raises(
        DataFormatError, match=r"point #1: expected finite coordinates, found \[nan, 0.0, 0.0\]"
    ):
        write_las(tmp_path / "nan.las", [bad])


def test_chunks_must_agree_on_labels(tmp_path: Path) -> None:
    with pytest.raises(DataFormatError, match="expected every chunk with labels"):
        write_las(tmp_path / "mixed.las", [random_cloud(3), random_cloud(3, labels=False)])


def test_writer_is_a_context_manager_and_counts(tmp_path: Path) -> None:
    with open_las_writer(tmp_path / "w.laz") as writer:
        writer.write(random_cloud(7, seed=1))
        writer.write(random_cloud(5, seed=2))
    assert writer.n_points == 12
    assert laspy.read(tmp_path / "w.laz").header.point_count == 12


def test_no_chunks_gives_a_valid_empty_file(tmp_path: Path) -> None:
    assert write_las(tmp_path / "empty.las", []) == 0
    assert read_las(tmp_path / "empty.las").n_points == 0
    assert laspy.read(tmp_path / "empty.las").header.point_count == 0


@pytest.mark.parametrize("suffix", SUFFIXES)
@pytest.mark.parametrize("keep", [0.5, 0.999])
def test_truncated_files_are_reported(tmp_path: Path, suffix: str, keep: float) -> None:
    path = tmp_path / f"scan{suffix}"
    write_las(path, [random_cloud(5000, seed=3)])
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])
    with pytest.raises(DataFormatError, match=rf"scan\{suffix}: expected .*(truncated|failed)"):
        list(iter_las(path, chunk_size=1000))


def test_truncated_header_and_garbage_are_reported(tmp_path: Path) -> None:
    path = tmp_path / "scan.las"
    write_las(path, [random_cloud(50)])
    path.write_bytes(path.read_bytes()[:400])  # inside the extra-bytes description
    with pytest.raises(DataFormatError, match=r"scan\.las: expected"):
        read_las(path)
    path.write_bytes(b"not a point cloud at all" * 20)
    with pytest.raises(DataFormatError, match=r"scan\.las: expected a LAS/LAZ file"):
        read_las(path)


def test_ign_sample_survives_to_the_millimetre(shared_data: Path, tmp_path: Path) -> None:
    from semantic3d.io.ascii import read_ascii_points

    folder = shared_data / "ign-lidarhd-toy"
    source = folder / "870000_6618000_subset.txt"
    if not source.is_file():
        pytest.skip("IGN sample not available")
    original = read_ascii_points(source, labels_path=folder / "870000_6618000_subset.labels")
    for suffix in SUFFIXES:
        write_las(tmp_path / f"ign{suffix}", split(original))
        back = read_las(tmp_path / f"ign{suffix}")
        assert np.array_equal(np.round(back.xyz * 1000), np.round(original.xyz * 1000))
        assert back.intensity.max() > 2047  # real intensities beyond the 12-bit range
        assert back.intensity.tolist() == original.intensity.tolist()
        assert np.array_equal(back.rgb, original.rgb)
        assert np.array_equal(back.labels, original.labels)


@pytest.mark.parametrize("suffix", SUFFIXES)
def test_the_wkt_bit_is_set_as_las_1_4_requires(tmp_path: Path, suffix: str) -> None:
    path = tmp_path / f"scan{suffix}"
    write_las(path, [random_cloud(10)])
    with laspy.open(path) as reader:
        assert reader.header.version == "1.4" and reader.header.point_format.id == 7
        assert reader.header.global_encoding.wkt
        assert not any(
            isinstance(v, laspy.vlrs.known.WktCoordinateSystemVlr) for v in reader.header.vlrs
        )


@pytest.mark.parametrize("crs", ["EPSG:2154", "epsg:2154"])
def test_a_crs_is_written_as_a_wkt_record(tmp_path: Path, crs: str) -> None:
    pyproj = pytest.importorskip("pyproj")
    path = tmp_path / "georef.las"
    cloud = random_cloud(50, offset=870_000.0)
    write_las(path, [cloud], crs=crs)
    with laspy.open(path) as reader:
        assert reader.header.global_encoding.wkt
        assert reader.header.parse_crs() == pyproj.CRS.from_epsg(2154)
    assert read_las(path).equals(cloud)  # the points are untouched


def test_an_unknown_crs_is_refused_before_writing(tmp_path: Path) -> None:
    pytest.importorskip("pyproj")
    with pytest.raises(
        CrsError,
        match=r"expected a coordinate reference system such as EPSG:2154, found 'EPSG:99999999'",
    ):
        write_las(tmp_path / "x.las", [random_cloud(5)], crs="EPSG:99999999")
    assert list(tmp_path.iterdir()) == []


def test_crs_applies_to_las_only(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"x\.ply: crs applies to LAS/LAZ output only"):
        write_points(tmp_path / "x.ply", [random_cloud(5)], crs="EPSG:2154")


def test_the_standard_intensity_field_is_shifted_and_documented(tmp_path: Path) -> None:
    cloud = random_cloud(4)
    cloud.intensity[:] = [-2048, -1, 0, 2047]
    write_las(tmp_path / "i.las", [cloud])
    las = laspy.read(tmp_path / "i.las")
    assert las.intensity.tolist() == [0, 2047, 2048, 4095]  # value + INTENSITY_OFFSET
    assert las[INTENSITY_DIMENSION].tolist() == [-2048, -1, 0, 2047]
    assert INTENSITY_OFFSET == 2048
    assert read_las(tmp_path / "i.las").intensity.tolist() == [-2048, -1, 0, 2047]
    (dimension,) = [d for d in las.point_format.extra_dimensions if d.name == INTENSITY_DIMENSION]
    assert dimension.description == "exact; intensity = this + 2048"
