"""The compiled counting sorts and box selection of the tile store against numpy references
(the expressions the store used before: stable argsorts, boolean masks)."""

from __future__ import annotations

from pathlib import Path
from unittest.mock import patch

import numba
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from semantic3d.core.errors import DataFormatError
from semantic3d.core.pointcloud import PointCloud
from semantic3d.core.threads import thread_limit
from semantic3d.spatial import TemporaryTileStore, TileGrid
from semantic3d.spatial import store as store_module
from semantic3d.spatial._kernels import order_by_code, stable_destinations
from semantic3d.spatial.store import TilePoints, TileStore, record_dtype, xyz_label_rows


def _numpy_tile_keys(grid: TileGrid, xyz: np.ndarray) -> np.ndarray:
    origin = np.asarray(grid.origin_xy, dtype=np.float64)
    cells = np.floor((xyz[:, :2] - origin) / grid.cell_size_m).astype(np.int64)
    return cells // grid.cells_per_tile


def _reference(cloud: PointCloud, keep: np.ndarray, grid: TileGrid, n_sub: int) -> dict:
    """The store's arrays by numpy: records grouped by tile (scan order inside), each
    tile's points ordered by sub-cell with a stable argsort, and the sub-cell offsets."""
    kept = np.flatnonzero(keep)
    keys = _numpy_tile_keys(grid, cloud.xyz)[kept]
    tiles = sorted({(int(x), int(y)) for x, y in keys})
    records = np.empty(kept.size, record_dtype(with_labels=cloud.labels is not None))
    order = np.empty(kept.size, np.int32)
    offsets = np.zeros((len(tiles), n_sub * n_sub + 1), np.int64)
    begin = 0
    for row, tile in enumerate(tiles):
        mine = kept[(keys[:, 0] == tile[0]) & (keys[:, 1] == tile[1])]
        end = begin + mine.size
        part = records[begin:end]
        part["xyz"], part["index"] = cloud.xyz[mine], mine
        part["intensity"], part["rgb"] = cloud.intensity[mine], cloud.rgb[mine]
        if cloud.labels is not None:
            part["labels"] = cloud.labels[mine]
        t_x0, t_y0, _, _ = grid.tile_bounds(tile)
        size = grid.tile_size_m / n_sub
        sx = np.clip(np.floor((part["xyz"][:, 0] - t_x0) / size), 0, n_sub - 1).astype(int)
        sy = np.clip(np.floor((part["xyz"][:, 1] - t_y0) / size), 0, n_sub - 1).astype(int)
        sub = sx * n_sub + sy
        order[begin:end] = np.argsort(sub, kind="stable")
        offsets[row, 1:] = np.cumsum(np.bincount(sub, minlength=n_sub * n_sub))
        begin = end
    return {"tiles": tiles, "records": records, "order": order, "offsets": offsets}


def _random_cloud(rng: np.random.Generator, n: int, *, labels: bool) -> PointCloud:
    return PointCloud.from_arrays(
        rng.uniform(-3.0, 3.0, (n, 3)),
        intensity=rng.integers(-2048, 2047, n),
        rgb=rng.integers(0, 256, (n, 3)),
        labels=rng.integers(0, 9, n) if labels else None,
    )


def _assert_store_is(store: TileStore, expected: dict) -> None:
    assert list(store.tiles) == expected["tiles"]
    points, order = store._arrays(store.n_points)  # in memory, or mapped from its files
    assert points.tobytes() == expected["records"].tobytes()
    np.testing.assert_array_equal(order, expected["order"])
    np.testing.assert_array_equal(store._offsets, expected["offsets"])


@settings(max_examples=25, deadline=None)
@given(
    n=st.integers(0, 400),
    chunk=st.integers(1, 150),
    tile=st.sampled_from([0.3, 1.0, 2.5]),
    n_sub=st.integers(1, 6),
    labels=st.booleans(),
    drop=st.integers(0, 3),
    seed=st.integers(0, 1000),
)
def test_store_arrays_equal_the_numpy_reference(
    n: int, chunk: int, tile: float, n_sub: int, labels: bool, drop: int, seed: int
) -> None:
    rng = np.random.default_rng(seed)
    cloud = _random_cloud(rng, n, labels=labels)
    keep = rng.integers(0, 4, n) >= drop
    grid = TileGrid.square(tile)
    with TemporaryTileStore.writer(grid=grid, subdivisions=n_sub) as writer:
        for start in range(0, n, chunk):
            writer.add(cloud[start : start + chunk], keep=keep[start : start + chunk])
        store = writer.close()
    _assert_store_is(store, _reference(cloud, keep, grid, n_sub))


@pytest.mark.parametrize("n_threads", [1, 3])
def test_a_store_of_many_blocks_equals_the_numpy_reference_on_any_threads(
    n_threads: int,
) -> None:
    """Chunks of more points than one thread counts alone: the counts of several blocks
    are summed before each block places its points."""
    rng = np.random.default_rng(n_threads)
    n = 230_000
    cloud = _random_cloud(rng, n, labels=True)
    keep = rng.random(n) < 0.9
    grid = TileGrid.square(1.7)
    with thread_limit(n_threads), TemporaryTileStore.writer(grid=grid, subdivisions=5) as writer:
        for start in range(0, n, 150_000):
            writer.add(cloud[start : start + 150_000], keep=keep[start : start + 150_000])
        store = writer.close()
    _assert_store_is(store, _reference(cloud, keep, grid, 5))


@settings(max_examples=30, deadline=None)
@given(
    n=st.integers(0, 200_000),
    n_slots=st.integers(1, 70),
    n_threads=st.sampled_from([1, 2, 5]),
    seed=st.integers(0, 1000),
)
def test_stable_destinations_equal_a_stable_argsort(
    n: int, n_slots: int, n_threads: int, seed: int
) -> None:
    slots = np.random.default_rng(seed).integers(0, n_slots + 1, n)
    with thread_limit(n_threads):
        destination, counts = stable_destinations(slots, n_slots, numba.get_num_threads())
    expected = np.empty(n, np.int64)
    expected[np.argsort(slots, kind="stable")] = np.arange(n)
    np.testing.assert_array_equal(destination, expected)
    np.testing.assert_array_equal(counts, np.bincount(slots, minlength=n_slots + 1))


@settings(max_examples=30, deadline=None)
@given(
    n=st.integers(0, 200_000),
    n_codes=st.integers(1, 1024),
    n_threads=st.sampled_from([1, 2, 5]),
    seed=st.integers(0, 1000),
)
def test_order_by_code_is_a_stable_argsort_on_any_threads(
    n: int, n_codes: int, n_threads: int, seed: int
) -> None:
    codes = np.random.default_rng(seed).integers(0, n_codes, n).astype(np.uint16)
    order = np.empty(n, np.int32)
    offsets = np.empty(n_codes + 1, np.int64)
    with thread_limit(n_threads):
        order_by_code(codes, n_codes, order, offsets, numba.get_num_threads())
    np.testing.assert_array_equal(order, np.argsort(codes, kind="stable"))
    np.testing.assert_array_equal(offsets[1:], np.cumsum(np.bincount(codes, minlength=n_codes)))
    assert offsets[0] == 0


@settings(max_examples=25, deadline=None)
@given(
    n=st.integers(0, 400),
    chunk=st.integers(1, 150),
    buffer_points=st.integers(1, 120),
    window=st.sampled_from([1, 3, 64]),
    n_sub=st.integers(1, 6),
    n_threads=st.sampled_from([1, 3]),
    seed=st.integers(0, 1000),
)
def test_a_spilled_store_sealed_a_window_at_a_time_equals_the_numpy_reference(
    n: int, chunk: int, buffer_points: int, window: int, n_sub: int, n_threads: int, seed: int
) -> None:
    """Tiles spilled to their files in turns, then sealed a few records at a time (their
    sub-cells coded window by window, ordered once the tile is whole)."""
    rng = np.random.default_rng(seed)
    cloud = _random_cloud(rng, n, labels=True)
    keep = rng.integers(0, 4, n) >= 1
    grid = TileGrid.square(1.0)
    with (
        patch.object(store_module, "_SEAL_WINDOW", window),
        thread_limit(n_threads),
        TemporaryTileStore.writer(
            grid=grid, subdivisions=n_sub, buffer_points=buffer_points
        ) as writer,
    ):
        for start in range(0, n, chunk):
            writer.add(cloud[start : start + chunk], keep=keep[start : start + chunk])
        spilled = writer.spilled_points
        with TemporaryTileStore.adopt(writer.close(), spilled_points=spilled) as store:
            assert (store.directory is None) == (spilled == 0)
            _assert_store_is(store, _reference(cloud, keep, grid, n_sub))


def test_a_damaged_tile_file_is_refused_while_sealing_and_nothing_is_left(
    tmp_path: Path,
) -> None:
    cloud = _random_cloud(np.random.default_rng(3), 500, labels=True)
    writer = store_module.TileStoreWriter(
        tmp_path / "store", grid=TileGrid.square(10.0, origin_xy=(-5.0, -5.0)), buffer_points=100
    )
    writer.add(cloud)
    (tile,) = writer._on_disk
    with writer._part(tile).open("ab") as part:
        part.write(b"\0" * 5)  # a record cut short
    with pytest.raises(DataFormatError, match=r"\.part: expected whole records of 40 bytes"):
        writer.close()
    assert list(tmp_path.iterdir()) == []


@settings(max_examples=40, deadline=None)
@given(
    origin=st.tuples(st.floats(-1e4, 1e4), st.floats(-1e4, 1e4)),
    cell=st.floats(0.01, 10.0),
    cells_per_tile=st.integers(1, 64),
    seed=st.integers(0, 1000),
)
def test_tile_keys_equal_the_numpy_expression(
    origin: tuple[float, float], cell: float, cells_per_tile: int, seed: int
) -> None:
    grid = TileGrid(origin_xy=origin, cell_size_m=cell, cells_per_tile=cells_per_tile)
    xyz = np.random.default_rng(seed).uniform(-2e4, 2e4, (500, 3))
    xyz[:10, :2] = np.asarray(origin) + cell * np.arange(10)[:, None]  # on cell edges
    np.testing.assert_array_equal(grid.tile_keys(xyz), _numpy_tile_keys(grid, xyz))


@settings(max_examples=25, deadline=None)
@given(
    n=st.sampled_from([50, 6000]),  # a small tile is filtered whole, a large one by sub-cells
    box=st.tuples(*[st.floats(-1.5, 1.5)] * 4),
    seed=st.integers(0, 100),
)
def test_box_selection_equals_a_boolean_mask(n: int, box: tuple, seed: int) -> None:
    rng = np.random.default_rng(seed)
    cloud = PointCloud.from_arrays(rng.uniform(-1.0, 1.0, (n, 3)), labels=rng.integers(0, 9, n))
    x0, y0 = min(box[0], box[2]), min(box[1], box[3])
    x1, y1 = max(box[0], box[2]), max(box[1], box[3])
    with TemporaryTileStore(
        [cloud], grid=TileGrid.square(4.0, origin_xy=(-2.0, -2.0)), subdivisions=16
    ) as store:
        got = store.read_box((x0, y0, x1, y1))
    x, y = cloud.xyz[:, 0], cloud.xyz[:, 1]
    expected = np.flatnonzero((x >= x0) & (x <= x1) & (y >= y0) & (y <= y1))
    np.testing.assert_array_equal(got.indices, expected)  # one tile: scan order
    assert got.cloud.equals(cloud[expected])


def test_rows_of_records_equal_numpy_columns() -> None:
    rng = np.random.default_rng(3)
    for labels in (True, False):
        records = np.zeros(7, record_dtype(with_labels=labels))
        records["xyz"] = rng.normal(size=(7, 3))
        if labels:
            records["labels"] = rng.integers(0, 9, 7)
        rows = xyz_label_rows(TilePoints.from_records(records))
        np.testing.assert_array_equal(rows[:, :3], records["xyz"])
        np.testing.assert_array_equal(rows[:, 3], records["labels"] if labels else 0.0)
