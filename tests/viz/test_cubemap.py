"""Cube maps: projection geometry, z-buffer, back-projection through the index face, files."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from semantic3d.core import PointCloud
from semantic3d.core.errors import OutputExistsError
from semantic3d.viz.cubemap import (
    FACE_NAMES,
    NO_POINT,
    CubeMapError,
    face_bases,
    project_points,
    render_cubemap,
)
from semantic3d.viz.cubemap_files import write_cubemap
from semantic3d.viz.station import (
    estimate_station,
    parse_station,
    read_sidecar_station,
    resolve_station,
)
from tests.factories import random_cloud

STATION = (10.0, -5.0, 1.5)


def _cloud(xyz: np.ndarray, labels: np.ndarray | None = None) -> PointCloud:
    n = len(xyz)
    rgb = (np.arange(n * 3).reshape(n, 3) % 256).astype(np.uint8)
    return PointCloud.from_arrays(np.asarray(xyz, float) + STATION, rgb=rgb, labels=labels)


@pytest.mark.parametrize("size", [8, 9])
def test_point_straight_ahead_lands_at_face_centre(size: int) -> None:
    forwards = face_bases()[:, 0]
    pixels = project_points(forwards * 7.0 + STATION, station=STATION, size=size)
    assert pixels.face.tolist() == list(range(6))
    assert pixels.row.tolist() == [size // 2] * 6
    assert pixels.col.tolist() == [size // 2] * 6
    np.testing.assert_allclose(pixels.range_m, 7.0, rtol=1e-6)


def test_right_and_up_axes_of_each_face() -> None:
    size = 10
    bases = face_bases()
    for face, (forward, right, up) in enumerate(bases):
        pixels = project_points(
            np.array([forward + 0.95 * right, forward + 0.95 * up]) + STATION,
            station=STATION,
            size=size,
        )
        assert pixels.face.tolist() == [face, face]
        assert (pixels.row[0], pixels.col[0]) == (5, 9)  # right edge, middle row
        assert (pixels.row[1], pixels.col[1]) == (0, 5)  # top edge, middle column


def test_seams_meet_edge_to_edge() -> None:
    size = 16
    eps = 1e-6
    # Between px and py: px's left edge meets py's right edge on the same row.
    side = project_points(
        np.array([[1.0, 1.0 - eps, 0.3], [1.0 - eps, 1.0, 0.3]]) + STATION,
        station=STATION,
        size=size,
    )
    assert [FACE_NAMES[f] for f in side.face] == ["px", "py"]
    assert side.col.tolist() == [0, size - 1]
    assert side.row[0] == side.row[1]
    # Between px and the top face: px's top row meets pz's bottom row, same column.
    top = project_points(
        np.array([[1.0, 0.2, 1.0 - eps], [1.0 - eps, 0.2, 1.0]]) + STATION,
        station=STATION,
        size=size,
    )
    assert [FACE_NAMES[f] for f in top.face] == ["px", "pz"]
    assert top.row.tolist() == [0, size - 1]
    assert top.col[0] == top.col[1]
    # An exact diagonal goes to the earlier face.
    tie = project_points(np.array([[1.0, 1.0, 0.0]]) + STATION, station=STATION, size=size)
    assert tie.face.tolist() == [0]


def test_points_behind_and_at_the_station() -> None:
    cloud = _cloud(np.array([[-3.0, 0.1, 0.2], [2.0, 0.0, 0.0], [0.0, 0.0, 0.0]]))
    pixels = project_points(cloud.xyz, station=STATION, size=8)
    assert [FACE_NAMES[f] if f >= 0 else None for f in pixels.face] == ["nx", "px", None]
    cubemap = render_cubemap([cloud], station=STATION, size=8)
    assert sorted(cubemap.point_index[cubemap.has_point].tolist()) == [0, 1]


def test_nearest_point_wins_whatever_the_order() -> None:
    ray = np.array([[5.0, 0.0, 0.0], [2.0, 0.0, 0.0], [9.0, 0.0, 0.0]])
    for order in ([0, 1, 2], [2, 1, 0], [1, 0, 2]):
        cubemap = render_cubemap([_cloud(ray[order])], station=STATION, size=4)
        shown = cubemap.point_index[0, 2, 2]
        assert order[shown] == 1
        assert cubemap.depth_m[0, 2, 2] == pytest.approx(2.0)


def test_equal_ranges_keep_the_first_point() -> None:
    same = _cloud(np.array([[3.0, 0.0, 0.0], [3.0, 0.0, 0.0]]))
    assert render_cubemap([same], station=STATION, size=4).point_index[0, 2, 2] == 0


def _reference_render(xyz: np.ndarray, size: int) -> np.ndarray:
    """Index faces by sorting (pixel, range, position): the numpy way, no splats."""
    pixels = project_points(xyz, station=STATION, size=size)
    flat = pixels.flat(size)
    keep = flat >= 0
    positions = np.flatnonzero(keep)
    order = np.lexsort((positions, pixels.range_m[keep], flat[keep]))
    first = np.ones(order.size, bool)
    first[1:] = flat[keep][order][1:] != flat[keep][order][:-1]
    index = np.full(6 * size * size, NO_POINT, np.int64)
    index[flat[keep][order][first]] = positions[order][first]
    return index.reshape(6, size, size)


def test_render_matches_a_sorting_reference_and_ignores_chunking() -> None:
    cloud = random_cloud(3000, seed=3)
    whole = render_cubemap([cloud], station=STATION, size=12)
    chunked = render_cubemap(
        [cloud[:1000], cloud[1000:1001], cloud[1001:]], station=STATION, size=12
    )
    np.testing.assert_array_equal(whole.point_index, _reference_render(cloud.xyz, 12))
    for name in ("point_index", "depth_m", "rgb", "labels"):
        np.testing.assert_array_equal(getattr(whole, name), getattr(chunked, name))


def test_back_projection_through_the_index_face_is_exact() -> None:
    cloud = random_cloud(2000, seed=4)
    cubemap = render_cubemap([cloud], station=STATION, size=16)
    assert cubemap.labels is not None
    shown = cubemap.point_index[cubemap.has_point]
    pixels = project_points(cloud.xyz[shown], station=STATION, size=16)
    faces, rows, cols = np.nonzero(cubemap.has_point)
    np.testing.assert_array_equal(pixels.face, faces)
    np.testing.assert_array_equal(pixels.row, rows)
    np.testing.assert_array_equal(pixels.col, cols)
    assert cloud.labels is not None
    np.testing.assert_array_equal(cubemap.labels[cubemap.has_point], cloud.labels[shown])
    np.testing.assert_array_equal(cubemap.rgb[cubemap.has_point], cloud.rgb[shown])


def test_splats_cover_neighbours_but_the_centre_pixel_is_exact() -> None:
    cloud = _cloud(np.array([[4.0, 0.0, 0.0], [8.0, -4.0, 0.0]]))
    plain = render_cubemap([cloud], station=STATION, size=32)
    splat = render_cubemap([cloud], station=STATION, size=32, splat_radius_px=1)
    assert plain.has_point.sum() == 2
    assert splat.has_point.sum() == 18
    for point in range(2):
        pixel = np.argwhere(plain.point_index == point)[0]
        assert splat.point_index[tuple(pixel)] == point


def test_label_faces_use_the_paper_colours() -> None:
    labels = np.array([0, 5], np.uint8)
    cloud = _cloud(np.array([[4.0, 0.0, 0.0], [0.0, 4.0, 0.0]]), labels)
    image = render_cubemap([cloud], station=STATION, size=4).label_image()
    assert image[0, 2, 2].tolist() == [255, 255, 255]  # unlabelled point: white
    assert image[1, 2, 2].tolist() == [128, 128, 128]  # buildings
    assert image[0, 0, 0].tolist() == [0, 0, 0]  # no point: black


def test_bad_parameters_are_refused() -> None:
    cloud = _cloud(np.ones((1, 3)))
    with pytest.raises(CubeMapError, match="size: expected a face edge"):
        render_cubemap([cloud], station=STATION, size=0)
    with pytest.raises(CubeMapError, match=r"splat_radius_px: expected 0\.\.16"):
        render_cubemap([cloud], station=STATION, size=4, splat_radius_px=-1)
    with pytest.raises(CubeMapError, match="station: expected 3 finite"):
        render_cubemap([cloud], station=(0.0, float("nan"), 0.0), size=4)


def test_written_faces_read_back(tmp_path: Path) -> None:
    cloud = random_cloud(500, seed=5)
    cubemap = render_cubemap([cloud], station=STATION, size=8)
    paths = write_cubemap(cubemap, tmp_path / "faces")
    assert len(paths) == 14
    face = np.asarray(Image.open(tmp_path / "faces" / "rgb_nz.png"))
    np.testing.assert_array_equal(face, cubemap.rgb[5])
    np.testing.assert_array_equal(np.load(tmp_path / "faces" / "index.npy"), cubemap.point_index)
    meta = json.loads((tmp_path / "faces" / "cubemap.json").read_text())
    assert meta["faces"] == list(FACE_NAMES) and meta["n_points"] == 500
    with pytest.raises(OutputExistsError, match=r"rgb_px\.png: already exists"):
        write_cubemap(cubemap, tmp_path / "faces")
    write_cubemap(cubemap, tmp_path / "faces", overwrite=True)


@pytest.mark.parametrize("text", ["1,2", "a,b,c", "1,2,3,4", "1,nan,2", ""])
def test_bad_station_strings(text: str) -> None:
    with pytest.raises(CubeMapError, match="station: expected x,y,z"):
        parse_station(text)


def test_station_from_the_simulator_sidecar(tmp_path: Path) -> None:
    scan = tmp_path / "street_station2.txt"
    scan.write_text("0 0 0 0 0 0 0\n")
    (tmp_path / "street.json").write_text(
        json.dumps(
            {
                "format": "semantic3d-simulation",
                "stations": [
                    {"points": "street_station1.txt", "position_m": [0, 0, 1]},
                    {"points": "street_station2.txt", "position_m": [6.0, -1.5, 1.8]},
                ],
            }
        )
    )
    assert read_sidecar_station(scan) == (6.0, -1.5, 1.8)
    assert resolve_station(scan).source == "sidecar"
    assert resolve_station(scan, station=(1.0, 2.0, 3.0)).position == (1.0, 2.0, 3.0)
    assert read_sidecar_station(tmp_path / "other.txt") is None


def test_station_estimate_finds_a_terrestrial_scanner() -> None:
    rng = np.random.default_rng(0)
    station = np.array([12.3, -4.1, 101.7])
    # Ground seen from 1.7 m: density falls with range² outside a blind cone of 1 m.
    ranges = np.exp(rng.uniform(0.0, np.log(30.0), 20_000))
    angles = rng.uniform(0, 2 * np.pi, ranges.size)
    ground = np.column_stack(
        [station[0] + ranges * np.cos(angles), station[1] + ranges * np.sin(angles)]
    )
    xyz = np.column_stack([ground, np.full(len(ground), 100.0)])
    wall = np.column_stack(
        [np.full(3000, station[0] + 15), rng.uniform(-20, 20, 3000), rng.uniform(100, 110, 3000)]
    )
    cloud = PointCloud.from_arrays(np.concatenate([xyz, wall]))
    found = estimate_station([cloud[:5000], cloud[5000:]])
    assert np.hypot(found[0] - station[0], found[1] - station[1]) < 0.7
    assert found[2] == pytest.approx(101.7, abs=0.1)
    with pytest.raises(CubeMapError, match="expected points"):
        estimate_station([PointCloud.empty()])
