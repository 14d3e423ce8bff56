"""Multi-scale features: names, per-level content, and tiled == whole-scan, bit for bit."""

from __future__ import annotations

import colorsys
import doctest
from collections.abc import Iterable
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import semantic3d.features.names as names_module
from semantic3d.core import PointCloud
from semantic3d.core.errors import ShapeError
from semantic3d.features import ConfigError, FeatureConfig, compute_multiscale_features, tiling
from semantic3d.features.attributes import compute_attribute_features
from semantic3d.features.multiscale import distinct_voxels
from semantic3d.features.names import CYLINDER_FEATURES, GEOMETRIC_FEATURES, parse_column_name
from semantic3d.features.scan import iter_scan_features
from semantic3d.features.tiling import TiledScan, TileFeatures
from semantic3d.io.chunks import rechunk
from tests.baselines.scene import make_street_scene

SMALL = FeatureConfig(base_voxel_size_m=0.1, n_levels=5, k_neighbours=8)


@pytest.fixture(scope="module")
def scene() -> PointCloud:
    return make_street_scene(3, size_m=24.0, spacing_m=0.2, with_colour=True)


def _chunks(cloud: PointCloud, size: int) -> list[PointCloud]:
    return list(rechunk(iter([cloud]), size, PointCloud.concatenate))


def test_names_doctests_pass() -> None:
    assert doctest.testmod(names_module).failed == 0


def test_columns_are_named_level_major() -> None:
    config = FeatureConfig(base_voxel_size_m=0.05, n_levels=3, colour=True)
    names = config.feature_names
    per_level = len(GEOMETRIC_FEATURES) + 1 + 3  # + cylinder_below + hue saturation value
    assert len(names) == config.n_features == 3 * per_level
    assert names[0] == "sum_of_eigenvalues@0.050m"
    assert parse_column_name(names[-1]) == ("value", 0.2)
    with pytest.raises(ValueError, match="expected '<feature>@<size>m'"):
        parse_column_name("planarity")


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"base_voxel_size_m": 0.0}, "base_voxel_size_m"),
        ({"n_levels": 0}, "n_levels: expected 1..16"),
        ({"k_neighbours": 2}, "k_neighbours: expected 3..256"),
        ({"n_levels": 2.5}, r"n_levels: expected 1..16, found 2\.5"),
        ({"k_neighbours": True}, "k_neighbours: expected 3..256, found True"),
    ],
)
def test_bad_feature_config_is_rejected(kwargs: dict, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        FeatureConfig(**kwargs)


def test_every_point_gets_a_finite_row_and_voxel_mates_share_it(scene: PointCloud) -> None:
    table = compute_multiscale_features(scene, config=SMALL)
    assert table.values.shape == (table.n_rows, SMALL.n_features)
    assert np.isfinite(table.values).all()
    assert table.point_row.shape == (scene.n_points,)
    assert table.n_rows < scene.n_points  # some voxels hold several points
    rows = table.point_values()
    ground = scene.labels == 1
    flat = rows[ground, table.names.index("surface_variation@0.400m")]
    upright = rows[ground, table.names.index("verticality@0.400m")]
    assert np.median(flat) < 0.05 and np.median(upright) < 0.1  # flat, normal along z
    walls = rows[scene.labels == 5, table.names.index("verticality@0.400m")]
    assert np.median(walls) > 0.5


def test_selected_points_get_the_rows_of_the_full_computation(scene: PointCloud) -> None:
    for per_point in (False, True):
        config = FeatureConfig(**{**_fields(SMALL), "per_point": per_point})
        full = compute_multiscale_features(scene, config=config).point_values()
        pick = np.array([5, 17, 17, 400, scene.n_points - 1])
        part = compute_multiscale_features(scene, config=config, point_indices=pick)
        assert np.array_equal(part.point_values(), full[pick])


def test_coarse_levels_with_fewer_points_than_k_use_all_of_them() -> None:
    xyz = np.array([[0.0, 0, 0], [0.3, 0, 0], [0, 0.4, 0], [0.01, 0.02, 0.9]]) + 5.0
    config = FeatureConfig(base_voxel_size_m=0.05, n_levels=6, k_neighbours=10)
    table = compute_multiscale_features(PointCloud.from_arrays(xyz), config=config)
    assert np.isfinite(table.values).all()
    top = table.values[:, -len(config.level_feature_names) :]
    assert np.all(top[:, GEOMETRIC_FEATURES.index("vertical_range")] == top[0, 13])  # one voxel
    column = config.level_feature_names.index("cylinder_below")
    assert np.all(top[:, column] == 0.0)  # one voxel in every top-level cylinder


@pytest.mark.parametrize(
    ("per_point", "whole_level_points", "cache_bytes", "part_points"),
    [
        (False, 0, 96 << 20, 1 << 40),
        (False, 5000, 96 << 20, 1 << 40),
        (True, 0, 96 << 20, 1 << 40),
        (False, 5000, 1, 1 << 40),
        (False, 0, 96 << 20, 97),
        (True, 5000, 96 << 20, 53),
    ],
    ids=[
        "voxel-halos",
        "voxel-coarse-levels-whole",
        "per-point-halos",
        "every-level-reread",
        "voxel-pyramids-in-parts",
        "per-point-pyramids-in-parts",
    ],
)
def test_tiled_features_equal_whole_scan_features_bit_for_bit(
    scene: PointCloud,
    per_point: bool,
    whole_level_points: int,
    cache_bytes: int,
    part_points: int,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # tiles of more than part_points points build their pyramids a part at a time
    monkeypatch.setattr(tiling, "PYRAMID_PART_POINTS", part_points)
    config = FeatureConfig(
        **{
            **_fields(SMALL),
            "per_point": per_point,
            "colour": True,
            "cylinder_features": CYLINDER_FEATURES,
        }
    )
    expected = compute_multiscale_features(scene, config=config).point_values()
    got = np.full_like(expected, np.nan)
    seen = np.zeros(scene.n_points, bool)
    with TiledScan(
        _chunks(scene, 7000),
        config=config,
        tile_size_m=3.2,
        workdir=tmp_path,
        whole_level_points=whole_level_points,
        cache_bytes=cache_bytes,
    ) as scan:
        assert len(scan.tiles) > 30  # small tiles: halos cross many tiles at coarse levels
        assert max(scan.store.count(tile) for tile in scan.tiles) > 3 * part_points or (
            part_points > scene.n_points
        )
        for tile in scan.iter_features():
            assert np.all(np.diff(tile.point_indices) > 0)
            got[tile.point_indices] = tile.table.point_values()
            seen[tile.point_indices] = True
            np.testing.assert_array_equal(tile.labels, scene.labels[tile.point_indices])
            assert tile.xyz is not None
            assert np.array_equal(tile.xyz, scene.xyz[tile.point_indices])
        # without the points' positions: the same rows, the positions None
        for tile in scan.iter_features(positions=False):
            assert tile.xyz is None
            assert np.array_equal(tile.table.point_values(), got[tile.point_indices])
            np.testing.assert_array_equal(tile.labels, scene.labels[tile.point_indices])
    assert seen.all()
    assert np.array_equal(got, expected)


def test_scan_features_in_memory_and_tiled_agree(scene: PointCloud) -> None:
    select = np.arange(0, scene.n_points, 11)
    blocks = {}
    for limit in (10**9, 0):
        rows = np.full((scene.n_points, SMALL.n_features), np.nan, np.float32)
        for block in iter_scan_features(
            _chunks(scene, 5000),
            config=SMALL,
            select=select,
            max_points_in_memory=limit,
            tile_size_m=6.4,
        ):
            assert block.n_scan_points == scene.n_points
            rows[block.point_indices] = block.table.point_values()
        blocks[limit] = rows
    assert np.array_equal(blocks[0][select], blocks[10**9][select])
    assert np.isnan(blocks[0][1]).all()  # not selected


def test_hsv_and_intensity_columns() -> None:
    attributes = np.array([[255.0, 0, 0, 10], [0, 0, 255, 30], [30, 60, 90, 0]])
    got = compute_attribute_features(
        attributes, np.array([[0, 1], [2, 2]], np.int64), colour=True, intensity=True
    )
    expected = [*colorsys.rgb_to_hsv(127.5 / 255, 0, 127.5 / 255), 20.0]
    np.testing.assert_allclose(got[0], expected, rtol=1e-6)
    np.testing.assert_allclose(
        got[1, :3], colorsys.rgb_to_hsv(30 / 255, 60 / 255, 90 / 255), rtol=1e-6
    )


def test_empty_cloud_and_bad_indices_are_rejected(scene: PointCloud) -> None:
    with pytest.raises(ShapeError, match="empty point cloud"):
        compute_multiscale_features(PointCloud.empty(), config=SMALL)
    with pytest.raises(ShapeError, match="point_indices: expected values in"):
        compute_multiscale_features(scene, config=SMALL, point_indices=[scene.n_points])


def _fields(config: FeatureConfig) -> dict:
    return {name: getattr(config, name) for name in config.__dataclass_fields__}


@pytest.mark.parametrize("size", [0, 1, 500])
def test_distinct_voxels_equals_numpy_unique(size: int) -> None:
    voxel_of_row = np.random.default_rng(size).integers(0, 300, size)
    needed, inverse = distinct_voxels(voxel_of_row)
    expected, expected_inverse = np.unique(voxel_of_row, return_inverse=True)
    np.testing.assert_array_equal(needed, expected)
    np.testing.assert_array_equal(inverse, expected_inverse)
    assert needed.dtype == inverse.dtype == np.int64


def test_level0_neighbours_are_each_rows_nearest_voxels_itself_first(scene: PointCloud) -> None:
    from semantic3d.features.multiscale import build_cloud_pyramid

    table = compute_multiscale_features(scene, config=SMALL)
    centres = build_cloud_pyramid(scene, config=SMALL).levels[0].xyz  # one row per voxel
    neighbours = table.neighbours
    assert neighbours is not None and neighbours.shape == (table.n_rows, SMALL.k_neighbours)
    np.testing.assert_array_equal(neighbours[:, 0], np.arange(table.n_rows))
    rng = np.random.default_rng(0)
    for row in rng.choice(table.n_rows, 200, replace=False):
        distance = np.linalg.norm(centres - centres[row], axis=1)
        listed = distance[neighbours[row]]
        assert np.all(np.diff(listed) >= 0)  # nearest first
        others = np.delete(distance, neighbours[row])
        assert listed[-1] <= others.min()  # no voxel left out is nearer
    # a subset of the points: voxels without a row are absent (-1), the others renumbered
    pick = np.flatnonzero(scene.xyz[:, 0] < np.median(scene.xyz[:, 0]))
    part = compute_multiscale_features(scene, config=SMALL, point_indices=pick)
    assert part.neighbours is not None
    assert np.any(part.neighbours == -1) and part.neighbours.max() < part.n_rows
    first_point = np.full(table.n_rows, scene.n_points)
    np.minimum.at(first_point, table.point_row, np.arange(scene.n_points))
    part_first = np.full(part.n_rows, scene.n_points)
    np.minimum.at(part_first, part.point_row, pick)
    whole_row = table.point_row[part_first]  # each part row's row in the whole table
    expected = table.neighbours[whole_row]
    kept = np.isin(expected, whole_row)
    got = part.neighbours
    np.testing.assert_array_equal(got == -1, ~kept)
    np.testing.assert_array_equal(whole_row[got[kept]], expected[kept])


@pytest.mark.parametrize("whole_level_points", [0, 10**9], ids=["level0-halos", "level0-whole"])
def test_tiled_neighbours_are_the_whole_scans_within_each_tile(
    scene: PointCloud, whole_level_points: int, tmp_path
) -> None:
    # each row named by the first point it holds: voxels never straddle tiles
    table = compute_multiscale_features(scene, config=SMALL)
    assert table.neighbours is not None
    first = np.full(table.n_rows, scene.n_points)
    np.minimum.at(first, table.point_row, np.arange(scene.n_points))
    tile_of_point = np.empty(scene.n_points, np.int64)
    got: dict[int, np.ndarray] = {}
    with TiledScan(
        _chunks(scene, 7000),
        config=SMALL,
        tile_size_m=3.2,
        workdir=tmp_path,
        whole_level_points=whole_level_points,
    ) as scan:
        for number, tile in enumerate(scan.iter_features()):
            tile_of_point[tile.point_indices] = number
            rows = tile.table
            assert rows.neighbours is not None
            row_first = np.full(rows.n_rows, scene.n_points)
            np.minimum.at(row_first, rows.point_row, tile.point_indices)
            named = np.where(rows.neighbours >= 0, row_first[rows.neighbours], -1)
            for row, point in enumerate(row_first):
                got[int(point)] = named[row]
    assert len(got) == table.n_rows
    for row, point in enumerate(first):
        expected = first[table.neighbours[row]]
        expected = np.where(tile_of_point[expected] == tile_of_point[point], expected, -1)
        np.testing.assert_array_equal(got[int(point)], expected)


@pytest.mark.parametrize("cylinders", [True, False])
def test_level_reach_is_the_reach_the_features_give(cylinders: bool) -> None:
    """The reach alone (what a tiled scan's first halo is estimated from) equals the one
    computed beside the features, with and without cylinder columns, at every level."""
    from semantic3d.features.multiscale import compute_level_features, level_reach
    from semantic3d.features.neighbourhoods import LevelIndex
    from semantic3d.features.pyramid import build_pyramid

    rng = np.random.default_rng(4)
    xyz = rng.gamma(1.5, 3.0, (20_000, 3)) * [1.0, 1.0, 0.3]
    config = FeatureConfig(n_levels=3, cylinders=cylinders)
    pyramid = build_pyramid(
        xyz, base_voxel_size_m=config.base_voxel_size_m, n_levels=3, origin=np.zeros(3)
    )
    for number, level in enumerate(pyramid.levels):
        index = LevelIndex(level.xyz, level.keys)
        queries = level.xyz[:: max(1, level.n_voxels // 300)] + 0.01
        _, expected = compute_level_features(
            index, np.empty((level.n_voxels, 0)), queries, config=config, level=number
        )
        reach = level_reach(index, queries, config=config, level=number)
        np.testing.assert_array_equal(reach, expected)
        if cylinders:
            assert reach.min() >= config.cylinder_radius_m(number)


def _every_level_by_tile(
    scene: PointCloud, config: FeatureConfig, tile_size_m: float, workdir: Path
) -> TiledScan:
    """The scene tiled, read in chunks of 7,000 points, every level described tile by tile
    (none whole)."""
    return TiledScan(
        _chunks(scene, 7000),
        config=config,
        tile_size_m=tile_size_m,
        workdir=workdir,
        whole_level_points=0,
    )


def test_a_tiles_levels_computed_in_parts_give_the_same_rows_and_neighbours(
    scene: PointCloud, tmp_path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A tile's level queries split into parts (strips, each from its own box, at the same
    time) give the rows and neighbour lists of the tile in one piece, and of the whole
    scan, bit for bit."""
    import semantic3d.features.tiling as tiling
    from semantic3d.core.threads import thread_limit

    config = FeatureConfig(**{**_fields(SMALL), "cylinder_features": CYLINDER_FEATURES})
    expected = compute_multiscale_features(scene, config=config).point_values()
    in_parts = []
    exact_level = TiledScan._exact_level

    def spied(self, *args, **options):  # type: ignore[no-untyped-def]
        in_parts.append(options.get("around") is not None)
        return exact_level(self, *args, **options)

    monkeypatch.setattr(TiledScan, "_exact_level", spied)

    def tiled(min_part: int) -> tuple[np.ndarray, dict]:
        monkeypatch.setattr(tiling, "_MIN_PART_QUERIES", min_part)
        got = np.full_like(expected, np.nan)
        neighbours = {}
        with thread_limit(3), _every_level_by_tile(scene, config, 12.8, tmp_path) as scan:
            for tile in scan.iter_features():  # each tile on the whole budget: in parts
                got[tile.point_indices] = tile.table.point_values()
                neighbours[tile.tile] = tile.table.neighbours
        return got, neighbours

    whole, whole_lists = tiled(10**9)  # one piece
    assert in_parts and not any(in_parts)
    in_parts.clear()
    parts, part_lists = tiled(40)  # every level of every tile in parts
    assert sum(in_parts) > 10
    assert np.array_equal(whole, expected)
    assert np.array_equal(parts, expected)
    assert whole_lists.keys() == part_lists.keys()
    for tile, lists in whole_lists.items():
        np.testing.assert_array_equal(part_lists[tile], lists)


def test_tiles_on_one_thread_of_a_large_map_cut_their_levels_into_parts_the_same_rows(
    scene: PointCloud, tmp_path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Mapped on 4 threads, a tile whose task has one thread still cuts its large levels
    into parts (which threads other tiles leave can join), every level's parts in one
    map: the rows and neighbour lists of the whole scan, bit for bit."""
    import semantic3d.features.tiling as tiling
    from semantic3d.core.threads import thread_budget, thread_limit

    config = FeatureConfig(**{**_fields(SMALL), "cylinder_features": CYLINDER_FEATURES})
    expected = compute_multiscale_features(scene, config=config).point_values()
    cuts: list[tuple[int, int]] = []  # (the task's threads, parts asked for)
    part_blocks = tiling.part_blocks

    def spied(queries, n_parts, reach):  # type: ignore[no-untyped-def]
        cuts.append((thread_budget(), n_parts))
        return part_blocks(queries, n_parts, reach)

    monkeypatch.setattr(tiling, "part_blocks", spied)
    monkeypatch.setattr(tiling, "_MIN_PART_QUERIES", 40)
    got = np.full_like(expected, np.nan)
    with thread_limit(4), _every_level_by_tile(scene, config, 6.4, tmp_path) as scan:
        assert len(scan.tiles) > 4
        for tile in scan.map_tiles(lambda features: features, n_threads=4):
            got[tile.point_indices] = tile.table.point_values()
    assert (1, tiling._GROWING_PARTS) in cuts  # a one-thread tile's level in parts
    assert np.array_equal(got, expected)


def test_pyramids_kept_in_memory_are_read_from_there_and_written_for_another_process(
    scene: PointCloud, tmp_path
) -> None:
    """On several threads the pyramid pass keeps its last pyramids in memory (at most a
    thread count of the cache's bytes) instead of writing them: rows read from them equal
    rows read from files, pickling writes them all first, and on one thread every pyramid
    is written as it is built."""
    import pickle
    from concurrent.futures import ThreadPoolExecutor

    from semantic3d.core.threads import thread_limit

    expected = compute_multiscale_features(scene, config=SMALL).point_values()

    def scan(threads: int, cache_bytes: int = 96 << 20) -> TiledScan:
        with thread_limit(threads):
            return TiledScan(
                _chunks(scene, 7000),
                config=SMALL,
                tile_size_m=3.2,
                workdir=tmp_path,
                cache_bytes=cache_bytes,
            )

    def files(tiled: TiledScan) -> set[str]:
        return {path.name for path in tiled.workdir.glob("*.pyramid.pickle")}

    def rows(tiles: Iterable[TileFeatures]) -> np.ndarray:
        got = np.full_like(expected, np.nan)
        for tile in tiles:
            got[tile.point_indices] = tile.table.point_values()
        return got

    with scan(1) as alone:  # one thread: every pyramid written as it is built
        assert not alone._kept and len(files(alone)) == len(alone.tiles)
        assert np.array_equal(rows(alone.iter_features()), expected)

    with scan(3) as kept:
        assert set(kept._kept) == set(kept.tiles)  # small pyramids: all fit
        assert not files(kept)
        with thread_limit(3):
            assert np.array_equal(rows(kept.map_tiles(lambda tile: tile)), expected)
        assert not files(kept)  # read from memory, never written
        with ThreadPoolExecutor(4) as pool:  # pickling writes them first, once
            copies = list(pool.map(lambda _: pickle.loads(pickle.dumps(kept)), range(4)))
        assert not kept._kept and kept._kept_bytes == 0
        assert len(files(kept)) == len(kept.tiles)
        for copy in copies:
            assert np.array_equal(rows(copy.iter_features()), expected)  # from the files

    with scan(2, cache_bytes=60_000) as bounded:  # room for a few: the others written
        assert 0 < len(bounded._kept) < len(bounded.tiles)
        assert bounded._kept_bytes <= 2 * 60_000
        assert len(files(bounded)) == len(bounded.tiles) - len(bounded._kept)
        assert np.array_equal(rows(bounded.iter_features()), expected)


def test_part_blocks_split_queries_into_runs_of_about_equal_work() -> None:
    """Where the level is dense (a cylinder holds many points) a part holds fewer queries;
    on an even level the parts hold equal counts."""
    from semantic3d.features.tiling import part_blocks

    rng = np.random.default_rng(1)
    sparse = rng.uniform([0, 0], [10, 10], (20_000, 2))
    dense = rng.uniform([10, 0], [11, 10], (20_000, 2))  # as many queries in a tenth of the area
    queries = np.c_[np.concatenate([sparse, dense]), np.zeros(40_000)]
    # two strips; a 2 m square holds 800 sparse queries or 4,000 dense ones: works of
    # 1,800 and 5,000 a query, so the first strip ends 6,400 queries into the dense ones
    blocks = part_blocks(queries, 2, 2.0)
    assert blocks[0][0] == 0 and blocks[-1][1] == queries.shape[0]
    sizes = [stop - start for start, stop, _, _ in blocks]
    assert len(sizes) == 2 and abs(sizes[0] - 26_400) < 1_000
    even = np.c_[rng.uniform(0, 10, (40_000, 2)), np.zeros(40_000)]
    even = even[np.argsort(np.floor(even[:, 0] / 0.1), kind="stable")]
    sizes = [stop - start for start, stop, _, _ in part_blocks(even, 2, 0.4)]
    assert np.all(np.abs(np.array(sizes) - 20_000) < 2_000)


@pytest.mark.parametrize(("n", "n_parts"), [(0, 4), (1, 4), (50_000, 1), (50_000, 2), (50_000, 14)])
def test_part_blocks_hold_every_query_once_in_about_square_blocks(n: int, n_parts: int) -> None:
    """Blocks are strips of consecutive queries cut along y: every query in exactly one,
    about ``n_parts`` of them, and on an even level about as wide as they are tall."""
    from semantic3d.features.tiling import part_blocks

    rng = np.random.default_rng(n_parts)
    xy = rng.uniform(0, 20, (n, 2))
    queries = np.c_[xy[np.argsort(np.floor(xy[:, 0] / 0.1), kind="stable")], np.zeros(n)]
    blocks = part_blocks(queries, n_parts, 0.4)
    seen = np.zeros(n, np.int64)
    extents = []
    for start, stop, y_low, y_high in blocks:
        assert 0 <= start < stop <= n and y_low < y_high
        inside = start + np.flatnonzero(
            (queries[start:stop, 1] >= y_low) & (queries[start:stop, 1] < y_high)
        )
        seen[inside] += 1
        if inside.size:
            extents.append(np.ptp(queries[inside, :2], axis=0))
    assert np.all(seen == 1)
    if n >= 50_000:
        across = max(1, round(np.sqrt(n_parts)))
        assert across * (-(-n_parts // across)) >= len(blocks) >= n_parts
        if n_parts >= 4:
            ratio = np.array([width / height for width, height in extents])
            assert np.all((ratio > 0.5) & (ratio < 2.0))


@settings(max_examples=40, deadline=None)
@given(
    x=st.tuples(st.floats(-5.0, 25.0), st.floats(0.0, 12.0)),
    y=st.tuples(st.floats(-5.0, 25.0), st.floats(0.0, 30.0)),
    level=st.integers(0, 3),
)
def test_a_boxs_rows_are_found_within_the_levels_columns_across_it(
    x: tuple[float, float], y: tuple[float, float], level: int
) -> None:
    """A level's rows inside a box, searched only in the run of voxel columns across the
    box's x range, are those searched in the whole level (voxel centres at cell edges,
    negative coordinates, boxes beyond the level and unbounded boxes included)."""
    from semantic3d.features._row_kernels import rows_in_box
    from semantic3d.features.pyramid import build_pyramid
    from semantic3d.features.tiling import _rows_across

    rng = np.random.default_rng(level)
    xyz = rng.uniform([-3.0, -3.0, 0.0], [20.0, 20.0, 4.0], (4000, 3))
    xyz[:500] = np.round(xyz[:500] / 0.2) * 0.2  # points on cell edges
    pyramid = build_pyramid(
        xyz, base_voxel_size_m=0.1, n_levels=4, origin=np.array([-3.0, -3.0, 0.0])
    )
    chosen = pyramid.levels[level]
    box = np.array([x[0], x[0] + x[1], y[0], y[0] + y[1]])
    for bounds in (box, np.array([-np.inf, np.inf, box[2], box[3]])):
        first, last = _rows_across(chosen.keys, bounds[0], bounds[1], chosen.voxel_size_m)
        got = first + rows_in_box(chosen.xyz[first:last], bounds)
        np.testing.assert_array_equal(got, rows_in_box(chosen.xyz, bounds))


def _with_lone_points(scene: PointCloud, lone_xyz: np.ndarray) -> PointCloud:
    """``scene`` plus points at ``lone_xyz`` (labelled 1, grey)."""
    n = lone_xyz.shape[0]
    lone = PointCloud(
        lone_xyz,
        intensity=np.zeros(n, np.int32),
        rgb=np.full((n, 3), 128, np.uint8),
        labels=np.ones(n, np.uint8),
    )
    return PointCloud.concatenate([scene, lone])


@pytest.mark.parametrize("brute_force_pairs", [1 << 26, 0], ids=["scanned", "tree"])
def test_a_tile_of_fewer_than_k_voxels_beside_dense_ones_is_exact_from_small_boxes(
    scene: PointCloud, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, brute_force_pairs: int
) -> None:
    """Three points in a tile of their own, 6 m past a dense scene's edge: at the fine
    levels the box of their tile and halo holds fewer than k level points, so their
    neighbours are looked for farther out. They get the whole scan's rows bit for bit, and
    their rows are computed among the few hundred level points of their neighbours' ball
    (a box grown by its own width and height described 800-2,100 of the scene's). The
    bound on their reach is the same whether the grown box's points are scanned or put in a
    tree (many queries)."""
    import semantic3d.features.tiling as tiling

    monkeypatch.setattr(tiling, "_BRUTE_FORCE_PAIRS", brute_force_pairs)

    config = FeatureConfig(**{**_fields(SMALL), "cylinder_features": CYLINDER_FEATURES})
    east = scene.xyz[:, 0].max()
    middle = np.median(scene.xyz, axis=0)
    cloud = _with_lone_points(
        scene,
        middle
        + np.array([[0.0, 0.0, 0.5], [0.2, 0.3, 0.6], [0.1, -0.2, 1.4]])
        + np.array([east - middle[0] + 6.0, 0.0, 0.0]),
    )
    expected = compute_multiscale_features(cloud, config=config).point_values()
    described: list[int] = []
    describe = tiling.compute_level_features

    def spied(index, *args, **options):  # type: ignore[no-untyped-def]
        described.append(index.n_points)
        return describe(index, *args, **options)

    got = np.full_like(expected, np.nan)
    with _every_level_by_tile(cloud, config, 3.2, tmp_path) as scan:
        at = np.floor((cloud.xyz[-1, :2] - scan.origin[:2]) / scan.tile_size_m)
        tile = (int(at[0]), int(at[1]))
        assert scan.store.count(tile) == 3
        for features in scan.iter_features():
            got[features.point_indices] = features.table.point_values()
        monkeypatch.setattr(tiling, "compute_level_features", spied)
        again = scan.tile_features(tile)
    assert again is not None
    assert np.array_equal(got, expected)
    np.testing.assert_array_equal(again.table.point_values(), expected[-3:])
    assert described.count(3) >= 2  # the first asks of the finest levels: the tile alone
    assert max(described) < 600


def test_a_scan_of_fewer_than_k_points_over_several_tiles_is_exact(tmp_path: Path) -> None:
    """Five points over three tiles, k = 8: every box holds fewer than k points until it
    holds the whole scan, and the rows are the whole scan's."""
    config = FeatureConfig(**{**_fields(SMALL), "cylinder_features": CYLINDER_FEATURES})
    xyz = np.array(
        [[0.5, 0.5, 0.0], [0.7, 0.4, 0.3], [4.1, 0.6, 0.2], [7.9, 1.0, 1.0], [8.2, 1.1, 0.4]]
    )
    cloud = _with_lone_points(
        PointCloud(np.empty((0, 3)), np.empty(0, np.int32), np.empty((0, 3), np.uint8)), xyz
    )
    expected = compute_multiscale_features(cloud, config=config).point_values()
    got = np.full_like(expected, np.nan)
    with _every_level_by_tile(cloud, config, 3.2, tmp_path) as scan:
        assert len(scan.tiles) == 3
        for features in scan.iter_features():
            got[features.point_indices] = features.table.point_values()
    assert np.array_equal(got, expected)


def test_tiles_get_threads_by_their_voxels_not_their_points(tmp_path: Path) -> None:
    """A tile of 20,000 points in a few voxels and one of 5,000 spread over thousands: the
    second has the work (one row a voxel) and gets the threads, and is described first."""
    from semantic3d.core.timeline import recording

    rng = np.random.default_rng(7)
    crowded = rng.uniform(0.0, 0.25, (20_000, 3)) + np.array([0.2, 0.2, 0.0])
    spread = rng.uniform(0.0, 3.0, (5_000, 3)) + np.array([3.3, 0.1, 0.0])
    cloud = _with_lone_points(
        PointCloud(np.empty((0, 3)), np.empty(0, np.int32), np.empty((0, 3), np.uint8)),
        np.concatenate([crowded, spread]),
    )
    with _every_level_by_tile(cloud, SMALL, 3.2, tmp_path) as scan, recording() as timeline:
        assert sorted(scan.store.count(tile) for tile in scan.tiles) == [5_000, 20_000]
        rows = list(scan.map_tiles(lambda features: features.point_indices.size, n_threads=4))
    assert sorted(rows) == [5_000, 20_000]
    tiles = sorted(
        (step.start_s, step.attrs["points"], step.attrs["threads"])
        for step in timeline.spans
        if step.name == "tile"
    )
    assert [(points, threads) for _, points, threads in tiles] == [(5_000, 4), (20_000, 1)]


def test_small_tiles_start_beside_the_large_ones_on_the_threads_their_work_earns(
    tmp_path: Path,
) -> None:
    """Two tiles with 1.66 and 1.13 of 4 threads' share of the work and ten small ones
    with 1.2 together: the large tiles get 2 and 1 threads, not their shares rounded up
    (2 and 2, all of them), and the small ones start while the large ones run, one thread
    each, instead of after them."""
    from semantic3d.core.timeline import recording

    rng = np.random.default_rng(11)
    first = rng.uniform(0.05, 3.15, (6_000, 3))
    second = rng.uniform(0.05, 3.15, (4_000, 3)) + np.array([0.0, 3.2, 0.0])
    small = [
        rng.uniform(0.05, 3.15, (400, 3)) + np.array([3.2 * i, 0.0, 0.0]) for i in range(1, 11)
    ]
    cloud = _with_lone_points(
        PointCloud(np.empty((0, 3)), np.empty(0, np.int32), np.empty((0, 3), np.uint8)),
        np.concatenate([first, second, *small]),
    )
    counts = [400] * 10 + [4_000, 6_000]
    with _every_level_by_tile(cloud, SMALL, 3.2, tmp_path) as scan, recording() as timeline:
        assert sorted(scan.store.count(tile) for tile in scan.tiles) == counts
        rows = list(scan.map_tiles(lambda features: features.point_indices.size, n_threads=4))
    assert sorted(rows) == counts
    tiles = [step for step in timeline.spans if step.name == "tile"]
    large = {step.attrs["points"]: step for step in tiles if step.attrs["points"] > 400}
    small_spans = [step for step in tiles if step.attrs["points"] == 400]
    assert {points: step.attrs["threads"] for points, step in large.items()} == {
        6_000: 2,
        4_000: 1,
    }
    assert {step.attrs["threads"] for step in small_spans} == {1}
    assert min(step.start_s for step in small_spans) < min(step.end_s for step in large.values())


@pytest.mark.parametrize("whole_level_points", [0, 1_000_000])  # levels by tile / some whole
def test_a_row_map_sees_a_tiles_rows_a_block_at_a_time_and_gives_the_whole_scans_results(
    scene: PointCloud, tmp_path, monkeypatch: pytest.MonkeyPatch, whole_level_points: int
) -> None:
    """With a row map, a tile's rows reach it in blocks of at most ``ROW_BLOCK`` rows as
    they are made (each level's distinct rows held, never the table): the mapped rows are
    those of the whole scan's rows, row for row, on one thread and on a map of 3, and the
    table keeps no feature values."""
    import semantic3d.features.multiscale as multiscale
    from semantic3d.core.threads import thread_limit
    from semantic3d.features.scan import map_scan_features

    monkeypatch.setattr(multiscale, "ROW_BLOCK", 50)
    expected_values = compute_multiscale_features(scene, config=SMALL).point_values()

    def of_rows(values: np.ndarray) -> np.ndarray:  # row by row: elementwise, every level
        return values.astype(np.float64) * 3.0 - 1.0

    expected = of_rows(expected_values)
    blocks: list[int] = []

    def row_map(values: np.ndarray) -> np.ndarray:
        assert values.dtype == np.float32 and values.shape[1] == SMALL.n_features
        blocks.append(values.shape[0])
        return of_rows(values)

    def mapped(tiles: Iterable[TileFeatures]) -> np.ndarray:
        got = np.full_like(expected, np.nan)
        for tile in tiles:
            assert tile.table.values.shape == (tile.table.n_rows, 0)
            assert tile.table.mapped is not None
            got[tile.point_indices] = tile.table.mapped[tile.table.point_row]
        return got

    with TiledScan(
        _chunks(scene, 7000),
        config=SMALL,
        tile_size_m=6.4,
        workdir=tmp_path,
        whole_level_points=whole_level_points,
    ) as scan:
        assert len(scan.tiles) > 4
        np.testing.assert_array_equal(mapped(scan.iter_features(row_map=row_map)), expected)
        assert max(blocks) <= 50 and len(blocks) > 2 * len(scan.tiles)
        with thread_limit(3):
            on_three = mapped(scan.map_tiles(lambda tile: tile, n_threads=3, row_map=row_map))
        np.testing.assert_array_equal(on_three, expected)
    for limit in (10**9, 7000):  # in memory, then tiled: the same mapped rows
        got = np.full_like(expected, np.nan)
        for block in map_scan_features(
            _chunks(scene, 7000),
            lambda block: block,
            config=SMALL,
            max_points_in_memory=limit,
            tile_size_m=6.4,
            workdir=tmp_path,
            row_map=row_map,
        ):
            assert block.table.mapped is not None and block.table.values.shape[1] == 0
            got[block.point_indices] = block.table.mapped[block.table.point_row]
        np.testing.assert_array_equal(got, expected)
