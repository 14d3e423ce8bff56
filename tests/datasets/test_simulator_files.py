"""``simulate``: the files it writes, their determinism, the sidecar poses and bad arguments."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from semantic3d.core import Semantic3DError
from semantic3d.datasets.simulator import (
    Primitive,
    Scanner,
    Scene,
    Shape,
    SimulationConfigError,
    Station,
    Surface,
    Terrain,
    build_scene,
    simulate,
    simulate_scan,
)
from semantic3d.io.ascii import read_ascii_points

GREY = Surface((128, 128, 128), 0.5)
NOISE = 0.003


def test_files_round_trip_and_match_the_result(tmp_path: Path) -> None:
    result = simulate("square", out=tmp_path, n_points=30_000, stations=2, seed=7)
    assert [p.name for p in sorted(tmp_path.iterdir())] == [
        "square.json",
        "square_station1.labels",
        "square_station1.txt",
        "square_station2.labels",
        "square_station2.txt",
    ]
    for scan in result.scans:
        cloud = read_ascii_points(scan.points_path, labels_path=scan.labels_path)
        assert cloud.n_points == scan.n_points == pytest.approx(30_000, rel=0.05)
        assert np.bincount(cloud.labels, minlength=9).tolist() == list(scan.class_counts)
        # The file holds what the library streams, rounded to millimetres.
        again = next(
            simulate_scan(
                build_scene("square", seed=7),
                scan.station,
                n_points=30_000,
                seed=7,
                chunk_size=scan.n_points,
            )
        )
        np.testing.assert_allclose(cloud.xyz, again.xyz, atol=0.0005 + 1e-9)
        np.testing.assert_array_equal(cloud.labels, again.labels)
    sidecar = json.loads(result.sidecar_path.read_text())
    assert sidecar["scene"] == "square" and sidecar["seed"] == 7
    assert sidecar["n_points_requested"] == 30_000
    assert [s["name"] for s in sidecar["stations"]] == ["station1", "station2"]
    assert sidecar["stations"][1]["labels"] == "square_station2.labels"
    assert sidecar["scanner"]["range_noise_m"] == Scanner().range_noise_m


def test_same_seed_same_bytes_other_seed_other_bytes(tmp_path: Path) -> None:
    runs = {
        key: simulate(
            "railway", out=tmp_path / key, n_points=20_000, stations=1, seed=seed, chunk_size=chunk
        )
        for key, seed, chunk in (("a", 11, 1 << 20), ("b", 11, 3000), ("c", 12, 1 << 20))
    }
    for name in ("railway_station1.txt", "railway_station1.labels", "railway.json"):
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes()
        assert (tmp_path / "a" / name).read_bytes() != (tmp_path / "c" / name).read_bytes()
    assert runs["a"].n_points == runs["b"].n_points


def test_poses_register_the_stations_onto_one_another(tmp_path: Path) -> None:
    """Take each scan into its scanner's own frame with the sidecar pose (as an instrument
    records it), check it looks like a levelled scanner's, then register both back with
    the poses: the faces of a fixed building coincide within the range noise."""
    terrain = Terrain((0.0, 0.01, 0.0, 0.0, 0.0, 0.0), 1, GREY)
    house = Primitive(Shape.BOX, (0.0, 12.0, 3.0), (6.0, 3.0, 4.0), 5, GREY, yaw_rad=0.3)
    stations = (
        Station(1, (-9.0, 0.0, 1.6), yaw_rad=0.4),
        Station(2, (8.0, -1.0, 1.8), yaw_rad=-2.1),
    )
    scene = Scene("pair", terrain, (house,), stations)
    scanner = Scanner(range_noise_m=NOISE, max_range_m=60.0, sweep_duration_s=100.0)
    result = simulate(scene, out=tmp_path, n_points=80_000, stations=2, seed=1, scanner=scanner)
    sidecar = json.loads(result.sidecar_path.read_text())
    registered = []
    for record, station in zip(sidecar["stations"], stations, strict=True):
        matrix = np.array(record["scanner_to_world"])
        assert record["position_m"] == list(station.position)
        assert record["yaw_deg"] == pytest.approx(math.degrees(station.yaw_rad))
        np.testing.assert_allclose(matrix[:3, 3], station.position)
        cloud = read_ascii_points(
            tmp_path / record["points"], labels_path=tmp_path / record["labels"]
        )
        homogeneous = np.c_[cloud.xyz, np.ones(cloud.n_points)]
        local = (np.linalg.inv(matrix) @ homogeneous.T).T[:, :3]
        ranges = np.linalg.norm(local, axis=1)
        elevation = np.degrees(np.arcsin(local[:, 2] / ranges))
        assert ranges.min() >= scanner.min_range_m - 0.01 and ranges.max() <= 60.01
        assert elevation.min() >= -60.2 and elevation.max() <= 90.0
        # The sweep starts at the scanner's zero azimuth: the first column lies along +x.
        first = np.degrees(np.arctan2(local[:50, 1], local[:50, 0]))
        np.testing.assert_allclose(first, 0.0, atol=0.05)
        back = (matrix @ np.c_[local, np.ones(len(local))].T).T[:, :3]
        registered.append((back, cloud.labels))
    # The house's south face (local y = -3) is seen from both stations.
    c, s = math.cos(0.3), math.sin(0.3)
    offsets = []
    for points, labels in registered:
        rel = points[labels == 5] - np.array(house.center)
        v = -s * rel[:, 0] + c * rel[:, 1]
        u = c * rel[:, 0] + s * rel[:, 1]
        face = (np.abs(v + 3.0) < 0.02) & (np.abs(u) < 5.5) & (np.abs(rel[:, 2]) < 3.5)
        assert np.count_nonzero(face) > 300
        offsets.append(v[face])
    for v in offsets:
        assert v.mean() == pytest.approx(-3.0, abs=0.0015)
        assert v.std() < 2 * NOISE
    assert offsets[0].mean() == pytest.approx(offsets[1].mean(), abs=0.0015)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"n_points": 0}, r"n_points: expected an integer in 1\.\.2_000_000_000, found 0"),
        ({"n_points": -5}, "found -5"),
        ({"scene": "moon"}, "unknown scene 'moon'"),
        ({"stations": 0}, r"stations: expected an integer in 1\.\.3, found 0"),
        ({"stations": 4}, "found 4"),
        ({"seed": -1}, "seed: expected a non-negative integer"),
        ({"chunk_size": 0}, "chunk_size must be a positive integer"),
    ],
)
def test_bad_arguments_raise_a_clear_value_error(
    tmp_path: Path, kwargs: dict[str, object], match: str
) -> None:
    arguments: dict[str, object] = {"scene": "street", "out": tmp_path, "n_points": 1000}
    arguments.update(kwargs)
    with pytest.raises(SimulationConfigError, match=match) as info:
        simulate(**arguments)  # type: ignore[arg-type]
    assert isinstance(info.value, ValueError) and isinstance(info.value, Semantic3DError)
    assert list(tmp_path.iterdir()) == []  # nothing written


def test_unwritable_output_folder_is_a_clear_error(tmp_path: Path) -> None:
    blocker = tmp_path / "file.txt"
    blocker.write_text("not a folder")
    with pytest.raises(
        SimulationConfigError, match=r"file\.txt/out: expected a writable output folder"
    ):
        simulate("street", out=blocker / "out", n_points=1000)


def test_simulate_scan_checks_its_arguments_before_iterating() -> None:
    scene = Scene("empty", Terrain((0.0,) * 6, 1, GREY), (), (Station(1, (0.0, 0.0, 1.7)),))
    with pytest.raises(SimulationConfigError, match="n_points"):
        simulate_scan(scene, scene.stations[0], n_points=0)
    with pytest.raises(SimulationConfigError, match="chunk_size"):
        simulate_scan(scene, scene.stations[0], n_points=10, chunk_size=-1)
    sky = Scene("sky", Terrain((0.0,) * 6, 1, GREY), (), (Station(1, (0.0, 0.0, 1.7)),))
    with pytest.raises(SimulationConfigError, match="no returns"):
        simulate_scan(sky, sky.stations[0], n_points=10, scanner=Scanner(elevation_min_deg=1.0))
