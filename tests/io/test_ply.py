from __future__ import annotations

from pathlib import Path

import numpy as np
import plyfile
import pytest
from hypothesis import given

from semantic3d.core import DataFormatError, PointCloud
from semantic3d.io.formats import estimate_point_count
from semantic3d.io.ply import (
    COUNT_WIDTH,
    LABEL_PROPERTY,
    iter_ply,
    open_ply_writer,
    read_ply,
    read_ply_header,
    write_ply,
)
from tests.factories import ROUND_TRIP, clouds, random_cloud, split


def _plyfile_write(
    path: Path, vertices: np.ndarray, *, text: bool = False, byte_order: str = "<"
) -> None:
    """A PLY written by plain plyfile, as other software would."""
    element = plyfile.PlyElement.describe(vertices, "vertex")
    plyfile.PlyData([element], text=text, byte_order=byte_order).write(str(path))


@given(cloud=clouds())
@ROUND_TRIP
def test_round_trip_is_exact(tmp_path_factory: pytest.TempPathFactory, cloud: PointCloud) -> None:
    path = tmp_path_factory.mktemp("ply") / "scan.ply"
    assert write_ply(path, split(cloud)) == cloud.n_points
    back = read_ply(path)
    assert back.equals(cloud)  # float64 coordinates and int32 intensities: nothing is lost


def test_chunks_have_the_asked_size_and_join_to_the_whole(tmp_path: Path) -> None:
    cloud = random_cloud(1000, seed=4, offset=870_000.0)
    write_ply(tmp_path / "scan.ply", [cloud])
    chunks = list(iter_ply(tmp_path / "scan.ply", chunk_size=400))
    assert [c.n_points for c in chunks] == [400, 400, 200]
    assert PointCloud.concatenate(chunks).equals(read_ply(tmp_path / "scan.ply"))


def test_file_is_what_plyfile_and_cloudcompare_expect(tmp_path: Path) -> None:
    cloud = random_cloud(300, seed=9, offset=870_000.0)
    path = tmp_path / "scan.ply"
    write_ply(path, [cloud[:100], cloud[100:]])
    header = read_ply_header(path)
    assert header.storage == "binary_little_endian"
    assert header.n_vertices == 300
    assert header.vertex_properties == (
        "x double",
        "y double",
        "z double",
        "intensity int",
        "red uchar",
        "green uchar",
        "blue uchar",
        f"{LABEL_PROPERTY} uchar",
    )
    # The count was patched into a fixed-width field: the line stays the same length.
    line = next(raw for raw in path.read_bytes().split(b"\n") if raw.startswith(b"element vertex"))
    assert line == b"element vertex " + b"300".ljust(COUNT_WIDTH)
    vertices = plyfile.PlyData.read(str(path))["vertex"].data  # the reference reader
    assert np.array_equal(vertices["x"], cloud.xyz[:, 0])
    assert np.array_equal(vertices["intensity"], cloud.intensity)
    assert np.array_equal(vertices["green"], cloud.rgb[:, 1])
    assert np.array_equal(vertices[LABEL_PROPERTY], cloud.labels)


def test_unlabelled_points_have_no_label_property(tmp_path: Path) -> None:
    cloud = random_cloud(10, labels=False)
    write_ply(tmp_path / "scan.ply", [cloud])
    assert all("label" not in p for p in read_ply_header(tmp_path / "scan.ply").vertex_properties)
    assert read_ply(tmp_path / "scan.ply").equals(cloud)


def test_empty_outputs_are_valid(tmp_path: Path) -> None:
    write_ply(tmp_path / "none.ply", [])
    write_ply(tmp_path / "empty.ply", [PointCloud.empty(with_labels=True)])
    assert read_ply(tmp_path / "none.ply").n_points == 0
    assert read_ply(tmp_path / "empty.ply").labels is not None
    assert plyfile.PlyData.read(str(tmp_path / "empty.ply"))["vertex"].count == 0


def test_foreign_float_file_with_cloudcompare_names(tmp_path: Path) -> None:
    n = 5
    vertices = np.zeros(
        n,
        dtype=[
            ("x", "f4"),
            ("y", "f4"),
            ("z", "f4"),
            ("red", "u2"),
            ("green", "u2"),
            ("blue", "u2"),
            ("scalar_intensity", "f4"),
            ("scalar_label", "f4"),
        ],
    )
    vertices["x"] = np.arange(n) * 0.5
    vertices["red"] = 65535
    vertices["green"] = 256 * 7
    vertices["scalar_intensity"] = [-1515, 0, 1, 2, 2047]
    vertices["scalar_label"] = [0, 1, 5, 8, 3]
    _plyfile_write(tmp_path / "cc.ply", vertices, byte_order=">")
    cloud = read_ply(tmp_path / "cc.ply")
    assert cloud.xyz[:, 0].tolist() == [0, 0.5, 1, 1.5, 2]
    assert cloud.rgb[0].tolist() == [255, 7, 0]  # 16-bit colours scaled down
    assert cloud.intensity.tolist() == [-1515, 0, 1, 2, 2047]
    assert cloud.labels is not None and cloud.labels.tolist() == [0, 1, 5, 8, 3]


def test_ascii_ply_is_read_too(tmp_path: Path) -> None:
    cloud = random_cloud(20, seed=2)
    vertices = np.zeros(20, dtype=[("x", "f8"), ("y", "f8"), ("z", "f8"), ("label", "u1")])
    for axis, name in enumerate("xyz"):
        vertices[name] = cloud.xyz[:, axis]
    vertices["label"] = cloud.labels
    _plyfile_write(tmp_path / "text.ply", vertices, text=True)
    back = read_ply(tmp_path / "text.ply")
    assert np.allclose(back.xyz, cloud.xyz, atol=1e-9)
    assert back.labels is not None and np.array_equal(back.labels, cloud.labels)
    assert not back.intensity.any() and not back.rgb.any()


@pytest.mark.parametrize("keep", [0.5, 0.99])
def test_truncated_body_is_reported(tmp_path: Path, keep: float) -> None:
    path = tmp_path / "scan.ply"
    write_ply(path, [random_cloud(1000)])
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])
    with pytest.raises(
        DataFormatError,
        match=r"scan\.ply: the header declares 1,000 vertices, which take at least 32,000 "
        r"bytes, found .* truncated file",
    ):
        read_ply(path)


@pytest.mark.parametrize("storage", ["binary_little_endian", "ascii"])
def test_a_vertex_count_beyond_the_file_size_is_refused_up_front(
    tmp_path: Path, storage: str
) -> None:
    path = tmp_path / "huge.ply"
    path.write_bytes(
        f"ply\nformat {storage} 1.0\nelement vertex 100000000000\nproperty double x\n"
        "property double y\nproperty double z\nend_header\n".encode()
        + b"1 2 3\n" * 40
    )
    least = "2,400,000,000,000" if storage != "ascii" else "600,000,000,000"
    message = rf"huge\.ply: the header declares 100,000,000,000 vertices, which take at least {least} bytes, found 240 bytes"
    with pytest.raises(DataFormatError, match=message):
        read_ply_header(path)
    with pytest.raises(DataFormatError, match=message):
        read_ply(path)
    with pytest.raises(DataFormatError, match=message):
        estimate_point_count(path)


def test_truncated_header_and_garbage_are_reported(tmp_path: Path) -> None:
    path = tmp_path / "scan.ply"
    path.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vert")
    with pytest.raises(DataFormatError, match=r"scan\.ply: expected a readable PLY file"):
        read_ply(path)
    path.write_bytes(b"\x00\x01 binary garbage" * 10)
    with pytest.raises(DataFormatError, match=r"scan\.ply: expected a readable PLY file"):
        read_ply(path)
    with pytest.raises(DataFormatError, match=r"scan\.ply: expected a PLY file"):
        read_ply_header(path)


def test_missing_vertex_element_or_coordinates_are_reported(tmp_path: Path) -> None:
    _plyfile_write(tmp_path / "faces.ply", np.zeros(2, dtype=[("a", "i4")]))
    data = (tmp_path / "faces.ply").read_bytes().replace(b"element vertex", b"element corner")
    (tmp_path / "faces.ply").write_bytes(data)
    with pytest.raises(DataFormatError, match=r"expected a 'vertex' element, found corner"):
        read_ply(tmp_path / "faces.ply")
    flat = np.zeros(2, dtype=[("x", "f8"), ("y", "f8")])
    _plyfile_write(tmp_path / "flat.ply", flat)
    with pytest.raises(DataFormatError, match=r"expected vertex properties x y z, missing z"):
        read_ply(tmp_path / "flat.ply")


def test_fractional_labels_are_rejected(tmp_path: Path) -> None:
    vertices = np.zeros(3, dtype=[("x", "f8"), ("y", "f8"), ("z", "f8"), ("scalar_label", "f4")])
    vertices["scalar_label"] = [1, 2.5, 3]
    _plyfile_write(tmp_path / "frac.ply", vertices)
    with pytest.raises(
        DataFormatError, match=r"expected integers in 0\.\.255 in vertex property 'scalar_label'"
    ):
        read_ply(tmp_path / "frac.ply")


def test_chunks_must_agree_on_labels_and_failures_leave_no_file(tmp_path: Path) -> None:
    path = tmp_path / "mixed.ply"
    with pytest.raises(DataFormatError, match="expected every chunk without labels"):
        write_ply(path, [random_cloud(3, labels=False), random_cloud(3)])
    assert not path.exists()


def test_writer_context_manager_counts(tmp_path: Path) -> None:
    with open_ply_writer(tmp_path / "w.ply") as writer:
        writer.write(random_cloud(4, seed=1))
        writer.write(random_cloud(6, seed=2))
    assert writer.n_points == 10
    assert read_ply_header(tmp_path / "w.ply").n_vertices == 10


def test_ign_sample_round_trips_exactly(shared_data: Path, tmp_path: Path) -> None:
    from semantic3d.io.ascii import read_ascii_points

    folder = shared_data / "ign-lidarhd-toy"
    if not (folder / "870000_6618000_subset.txt").is_file():
        pytest.skip("IGN sample not available")
    original = read_ascii_points(
        folder / "870000_6618000_subset.txt", labels_path=folder / "870000_6618000_subset.labels"
    )
    write_ply(tmp_path / "ign.ply", split(original))
    assert read_ply(tmp_path / "ign.ply").equals(original)
