"""Point-centred cubes against slow references; tiles, determinism, model files, errors."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numba
import numpy as np
import pytest
import torch

from semantic3d.baselines.cnn.config import CnnConfig, config_from_dict
from semantic3d.baselines.cnn.cubes import CentringError, build_occupancy, compute_cubes
from semantic3d.baselines.cnn.model import CnnModel
from semantic3d.baselines.cnn.network import build_network
from semantic3d.baselines.cnn.persistence import load_model, read_model_header, save_model
from semantic3d.baselines.cnn.point_cubes import (
    SKYLINE_MAX_POINTS,
    build_cell_summaries,
    fill_point_cubes,
)
from semantic3d.baselines.common.prediction import predict_scan
from semantic3d.core import PointCloud
from semantic3d.core.errors import ConfigError, ShapeError
from semantic3d.io.formats import read_points
from semantic3d.io.labels import read_labels
from semantic3d.spatial.grid import TileGrid
from semantic3d.spatial.store import TemporaryTileStore
from semantic3d.spatial.voxels import pack_keys
from tests.baselines.cnn.conftest import TINY

SIZE = 8
POINT = dataclasses.replace(TINY, cubes=dataclasses.replace(TINY.cubes, centring="point"))


def reference(
    points: np.ndarray, queries: np.ndarray, origin: np.ndarray, sizes: tuple[float, ...]
) -> np.ndarray:
    """The definition, point by point: i = (A_q - A_p) + C/2 - [t_q < t_p] per axis."""
    out = np.zeros((len(queries), len(sizes), SIZE, SIZE, SIZE), np.float32)
    for s, v in enumerate(sizes):
        f = (points - origin) / v
        cells = np.floor(f)
        fractions = f - cells
        f_query = (queries - origin) / v
        query_cells = np.floor(f_query)
        query_fractions = f_query - query_cells
        for q in range(len(queries)):
            index = (cells - query_cells[q]).astype(np.int64) + SIZE // 2
            index -= fractions < query_fractions[q]
            inside = np.all((index >= 0) & (index < SIZE), axis=1)
            i, j, k = index[inside].T
            out[q, s, i, j, k] = 1.0
    return out


def point_cubes(
    points: np.ndarray, queries: np.ndarray, origin: np.ndarray, sizes: tuple
) -> np.ndarray:
    occupancy = build_occupancy(points, origin=origin, voxel_sizes_m=sizes, centring="point")
    return compute_cubes(occupancy, queries, cube_voxels=SIZE, centring="point")


def test_random_clouds_with_borders_and_duplicates_follow_the_definition() -> None:
    rng = np.random.default_rng(0)
    sizes = (0.125, 0.25, 1.0)
    origin = np.array([-4.0, -4.0, -2.0])
    lattice = rng.integers(-32, 32, (1500, 3)) * 0.0625  # exact: on voxel borders, and ties
    dense = rng.uniform(0, 1, (4000, 3)) * [2.0, 2.0, 0.5]  # cells of tens of points at 1 m
    crowded = rng.uniform(0, 1, (3000, 3)) * [0.9, 0.9, 0.9] + [-3.0, 1.0, 0.0]  # one cell
    u, v = rng.uniform(0, 1, (2, 4000))
    on = (u + v > 0.5) & (u + v <= 1.5)
    tilted = np.column_stack([2 + u[on], -4 + v[on], 1.5 - u[on] - v[on]])  # its own skyline
    points = np.concatenate([lattice, dense, crowded, tilted, lattice[:200]])  # duplicates
    queries = np.concatenate(
        [points[::97], rng.integers(-32, 32, (20, 3)) * 0.03125, [[-2.5, 1.5, 0.5]]]
    )
    cubes = point_cubes(points, queries, origin, sizes)
    np.testing.assert_array_equal(cubes, reference(points, queries, origin, sizes))
    assert 0.05 < cubes.mean() < 0.95
    summary = build_cell_summaries(points, origin=origin, voxel_size_m=1.0)
    counts = dict(zip(summary.keys.tolist(), np.diff(summary.starts).tolist(), strict=True))
    cell = {
        name: int(pack_keys(np.floor((p[:1] - origin) / 1.0).astype(np.int64))[0])
        for name, p in (("crowded", crowded), ("tilted", tilted))
    }
    assert counts[cell["crowded"]] < 300  # 3,000 points in a volume: short skylines
    assert counts[cell["tilted"]] == len(tilted) > SKYLINE_MAX_POINTS  # a skyline too long


def test_away_from_borders_the_cube_is_floor_of_the_offset() -> None:
    rng = np.random.default_rng(1)
    sizes = (0.05, 0.2, 0.4)
    points = rng.uniform(0, 4, (3000, 3)) * [1, 1, 0.4]
    queries = points[::150]
    cubes = point_cubes(points, queries, np.zeros(3), sizes)
    plain = np.zeros_like(cubes)
    for s, v in enumerate(sizes):
        for q, p in enumerate(queries):
            index = np.floor((points - p) / v).astype(np.int64) + SIZE // 2
            inside = np.all((index >= 0) & (index < SIZE), axis=1)
            plain[q, s, *index[inside].T] = 1.0
    np.testing.assert_array_equal(cubes, plain)
    centre = cubes[:, :, SIZE // 2, SIZE // 2, SIZE // 2]
    assert centre.all()  # each point lies in its own cube's voxel (C/2, C/2, C/2)


def test_empty_neighbourhoods_give_empty_cubes() -> None:
    sizes = (0.1, 0.4)
    points = np.random.default_rng(2).uniform(0, 2, (500, 3))
    far = np.array([[60.0, 60.0, 0.0], [-40.0, 3.0, 9.0]])
    cubes = point_cubes(points, np.concatenate([points[:3], far]), np.zeros(3), sizes)
    assert cubes[:3].any() and not cubes[3:].any()
    assert not point_cubes(np.empty((0, 3)), points[:4], np.zeros(3), sizes).any()


def test_georeferenced_coordinates() -> None:
    rng = np.random.default_rng(3)
    sizes = (0.025, 0.1, 0.4)
    local = rng.uniform(0, 3, (1500, 3)) * [1, 1, 0.2]
    shift = np.array([870_000.0, 6_617_000.0, 0.0])  # whole 0.4 m cells, as the origin
    queries = local[::60]
    near_zero = point_cubes(local, queries, np.zeros(3), sizes)
    far = point_cubes(local + shift, queries + shift, shift, sizes)
    np.testing.assert_array_equal(far, reference(local + shift, queries + shift, shift, sizes))
    # The shift moves each coordinate by ~1e-10 m: cubes of random points do not change.
    np.testing.assert_array_equal(far, near_zero)


def test_deterministic_whatever_the_threads() -> None:
    rng = np.random.default_rng(4)
    sizes = (0.1, 0.5)
    points = rng.uniform(0, 3, (5000, 3))
    first = point_cubes(points, points[::40], np.zeros(3), sizes)
    before = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        single = point_cubes(points, points[::40], np.zeros(3), sizes)
    finally:
        numba.set_num_threads(before)
    np.testing.assert_array_equal(first, single)
    np.testing.assert_array_equal(first, point_cubes(points, points[::40], np.zeros(3), sizes))


def test_a_tile_with_a_halo_of_the_reach_gives_the_whole_scan_cubes(tmp_path: Path) -> None:
    cubes = POINT.cubes
    v = max(cubes.voxel_sizes_m)
    rng = np.random.default_rng(5)
    # A lattice of v/2: many pairs lie exactly C/2 voxels apart across tile edges.
    xyz = rng.integers(0, 48, (6000, 3)) * (v / 2) * [1, 1, 0.25]
    cloud = PointCloud.from_arrays(xyz)
    origin = np.zeros(3)
    whole_occupancy = build_occupancy(
        xyz, origin=origin, voxel_sizes_m=cubes.voxel_sizes_m, centring="point"
    )
    whole = compute_cubes(whole_occupancy, xyz, cube_voxels=SIZE, centring="point")
    assert cubes.reach_m >= SIZE / 2 * v
    with TemporaryTileStore([cloud], grid=TileGrid.square(8.0), workdir=tmp_path) as store:
        assert len(store.tiles) > 1
        short = SIZE / 2 * v - v / 4
        for halo, equal in ((cubes.reach_m, True), (short, False)):
            same = []
            for tile in store.tiles:
                data = store.read(tile, halo_m=halo)
                core = np.asarray(data.core.cloud.xyz)
                neighbourhood = np.concatenate([core, np.asarray(data.halo.cloud.xyz)])
                occupancy = build_occupancy(
                    neighbourhood,
                    origin=origin,
                    voxel_sizes_m=cubes.voxel_sizes_m,
                    centring="point",
                )
                tiled = compute_cubes(occupancy, core, cube_voxels=SIZE, centring="point")
                same.append(np.array_equal(tiled, whole[np.asarray(data.core.indices)]))
            assert all(same) == equal  # a halo of C/2 voxels minus a quarter is too short


def _untrained(config: CnnConfig, network: Any = None) -> CnnModel:
    torch.manual_seed(0)
    return CnnModel(
        network if network is not None else build_network(config.cubes, config.network),
        config=config,
        label_values=(1, 3, 5, 8),
        training_scans=("train",),
        seed=0,
        n_batches_trained=0,
        training_time_s=0.0,
        package_version="0",
    )


def test_tiled_labels_equal_whole_scan_labels(
    trained: Any, cnn_scans: Path, tmp_path: Path
) -> None:
    model = _untrained(POINT, trained.network)  # weights that tell cubes apart
    cloud = read_points(cnn_scans / "test.txt")
    whole = model.label_cloud(cloud)
    run = predict_scan(model, cnn_scans / "test.txt", out_path=tmp_path / "test.labels")
    assert run.tiled
    np.testing.assert_array_equal(read_labels(tmp_path / "test.labels"), whole)
    assert len(np.unique(whole)) > 1
    doubled = PointCloud.concatenate([cloud[:400], cloud[:400]])  # every point twice
    per_point = dataclasses.replace(
        POINT, prediction=dataclasses.replace(POINT.prediction, deduplicate=False)
    )
    np.testing.assert_array_equal(
        model.label_cloud(doubled), _untrained(per_point, trained.network).label_cloud(doubled)
    )
    corner = dataclasses.replace(POINT, cubes=dataclasses.replace(POINT.cubes, centring="corner"))
    assert not np.array_equal(_untrained(corner, trained.network).label_cloud(cloud), whole)


def test_model_files_record_the_centring_and_old_ones_load_as_corner(tmp_path: Path) -> None:
    path = save_model(_untrained(POINT), tmp_path / "point.cnn")
    assert read_model_header(path)["config"]["cubes"]["centring"] == "point"
    assert load_model(path).config == POINT
    raw = path.read_bytes()
    magic, rest = raw[:8], raw[8:]
    line, payload = rest.split(b"\n", 1)
    header = json.loads(line)
    del header["config"]["cubes"]["centring"]  # a file written before the field existed
    (tmp_path / "old.cnn").write_bytes(magic + json.dumps(header).encode() + b"\n" + payload)
    old = load_model(tmp_path / "old.cnn")
    assert old.config.cubes.centring == "corner"
    assert old.config == dataclasses.replace(
        POINT, cubes=dataclasses.replace(POINT.cubes, centring="corner")
    )


def test_the_paper_preset_centres_on_the_point_and_bad_values_are_refused() -> None:
    assert CnnConfig().cubes.centring == "point"
    assert config_from_dict({"preset": "paper"}).cubes.centring == "point"
    with pytest.raises(
        ConfigError,
        match=r"\[cubes\] centring: expected one of \['point', 'corner'\], found 'middle'",
    ):
        config_from_dict({"cubes": {"centring": "middle"}})
    points = np.zeros((3, 3))
    corner = build_occupancy(points, origin=np.zeros(3), voxel_sizes_m=(0.1,))
    with pytest.raises(CentringError, match="occupancy: expected cell summaries for point-centred"):
        compute_cubes(corner, points, cube_voxels=SIZE, centring="point")
    with pytest.raises(
        CentringError, match=r"centring: expected one of \['point', 'corner'\], found 'edge'"
    ):
        build_occupancy(points, origin=np.zeros(3), voxel_sizes_m=(0.1,), centring="edge")
    summaries = [build_cell_summaries(points, origin=np.zeros(3), voxel_size_m=0.1)]
    with pytest.raises(ShapeError, match=r"xyz: expected \(n, 3\) coordinates, found \(3, 2\)"):
        fill_point_cubes(
            summaries, np.zeros((3, 2)), origin=np.zeros(3), voxel_sizes_m=(0.1,), cube_voxels=SIZE
        )
    with pytest.raises(ShapeError, match=r"summaries: expected one per scale \(2\), found 1"):
        fill_point_cubes(
            summaries, points, origin=np.zeros(3), voxel_sizes_m=(0.1, 0.2), cube_voxels=SIZE
        )


@pytest.mark.gpu
def test_cuda_prediction_of_point_centred_cubes_agrees_with_the_cpu(cnn_scans: Path) -> None:
    if not torch.cuda.is_available():
        pytest.skip("no CUDA device")
    cloud = read_points(cnn_scans / "test.txt")
    on_cpu = _untrained(POINT).label_cloud(cloud)
    on_gpu = _untrained(POINT).to("cuda").label_cloud(cloud)  # GPU cubes, float16 network
    assert np.mean(on_gpu == on_cpu) > 0.99
