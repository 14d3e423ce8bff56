"""TileStore: cores partition the scan, halos of any width equal a brute-force search."""

from __future__ import annotations

import multiprocessing
import pickle
import tracemalloc
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from semantic3d.core.errors import DataFormatError, ShapeError
from semantic3d.core.pointcloud import PointCloud
from semantic3d.core.threads import thread_limit
from semantic3d.io.cache import write_cache
from semantic3d.spatial import (
    TemporaryTileStore,
    TileGrid,
    TileJob,
    TileStore,
    build_tile_store,
    open_cache_tiles,
)
from semantic3d.spatial import store as store_module
from tests.mappings import mapped_kib


def _cloud(n: int, *, seed: int = 5, extent: float = 3.0, labels: bool = True) -> PointCloud:
    rng = np.random.default_rng(seed)
    return PointCloud.from_arrays(
        rng.uniform(-extent, extent, (n, 3)),
        intensity=rng.integers(-2048, 2047, n),
        rgb=rng.integers(0, 256, (n, 3)),
        labels=rng.integers(0, 9, n) if labels else None,
    )


def _chunks(cloud: PointCloud, size: int) -> list[PointCloud]:
    return [cloud[start : start + size] for start in range(0, cloud.n_points, size)]


def _brute_halo(cloud: PointCloud, grid: TileGrid, tile: tuple[int, int], halo_m: float) -> set:
    x0, y0, x1, y1 = grid.tile_bounds(tile)
    keys = grid.tile_keys(cloud.xyz)
    outside = (keys[:, 0] != tile[0]) | (keys[:, 1] != tile[1])
    x, y = cloud.xyz[:, 0], cloud.xyz[:, 1]
    near = (x >= x0 - halo_m) & (x <= x1 + halo_m) & (y >= y0 - halo_m) & (y <= y1 + halo_m)
    return set(np.flatnonzero(outside & near).tolist())


def test_cores_partition_the_scan_in_scan_order(tmp_path: Path) -> None:
    cloud = _cloud(5_000)
    grid = TileGrid.square(1.0)
    store = build_tile_store(_chunks(cloud, 700), tmp_path / "store", grid=grid)
    assert store.n_points == 5_000 and store.has_labels
    assert len(store.tiles) == 36 and list(store.tiles) == sorted(store.tiles)
    seen = []
    for tile in store.tiles:
        core = store.read_core(tile)
        assert store.count(tile) == core.n_points
        assert np.all(np.diff(core.indices) > 0)  # scan order
        assert np.all(grid.tile_keys(core.cloud.xyz) == tile)
        expected = cloud[core.indices]
        assert core.cloud.equals(expected)  # every column comes back exactly
        copied = core.copied()  # contiguous private copies, the same points
        assert copied.cloud.equals(expected) and copied.cloud.xyz.flags.c_contiguous
        np.testing.assert_array_equal(copied.indices, core.indices)
        assert copied.cloud.xyz.flags.writeable and copied.indices.flags.c_contiguous
        seen.append(core.indices)
    np.testing.assert_array_equal(np.sort(np.concatenate(seen)), np.arange(5_000))
    assert store.read_core((99, 99)).n_points == 0


@pytest.mark.parametrize("halo_m", [0.0, 0.03, 0.4, 1.0, 2.6])
def test_halos_of_any_width_equal_a_brute_force_search(tmp_path: Path, halo_m: float) -> None:
    cloud = _cloud(4_000)
    grid = TileGrid(origin_xy=(0.25, -0.1), cell_size_m=0.25, cells_per_tile=4)
    store = build_tile_store(_chunks(cloud, 1_000), tmp_path / "s", grid=grid, subdivisions=8)
    for tile in store.tiles:
        halo = store.read_halo(tile, halo_m)
        assert set(halo.indices.tolist()) == _brute_halo(cloud, grid, tile, halo_m)
        assert halo.cloud.equals(cloud[halo.indices])


def test_halos_through_the_sub_cell_index_of_large_tiles(tmp_path: Path) -> None:
    """Tiles above the small-tile threshold read only the border sub-cells."""
    cloud = _cloud(60_000, extent=2.0)
    grid = TileGrid.square(2.0)
    store = build_tile_store([cloud], tmp_path / "s", grid=grid, subdivisions=16)
    assert min(store.count(tile) for tile in store.tiles) > 4096
    for halo_m in (0.01, 0.3):
        for tile in store.tiles:
            got = store.read_halo(tile, halo_m).indices
            assert got.size == np.unique(got).size
            assert set(got.tolist()) == _brute_halo(cloud, grid, tile, halo_m)


def test_read_box_equals_a_brute_force_search(tmp_path: Path) -> None:
    cloud = _cloud(3_000)
    store = build_tile_store([cloud], tmp_path / "s", grid=TileGrid.square(0.7))
    box = (-1.3, 0.2, 0.9, 2.5)
    x, y = cloud.xyz[:, 0], cloud.xyz[:, 1]
    inside = (x >= box[0]) & (x <= box[2]) & (y >= box[1]) & (y <= box[3])
    got = store.read_box(box).indices
    assert sorted(got.tolist()) == np.flatnonzero(inside).tolist()


def test_spilling_to_disk_changes_nothing(tmp_path: Path) -> None:
    cloud = _cloud(3_000)
    grid = TileGrid.square(1.5)
    memory = build_tile_store(_chunks(cloud, 250), tmp_path / "m", grid=grid)
    disk = build_tile_store(_chunks(cloud, 250), tmp_path / "d", grid=grid, buffer_points=100)
    assert memory.tiles == disk.tiles
    for tile in memory.tiles:
        for width in (0.0, 0.2):
            a, b = memory.read(tile, halo_m=width), disk.read(tile, halo_m=width)
            np.testing.assert_array_equal(a.core.indices, b.core.indices)
            np.testing.assert_array_equal(a.halo.indices, b.halo.indices)
    assert not list(tmp_path.glob(".*partial"))  # no staging folder left behind


@pytest.mark.parametrize("buffer_points", [100, 1 << 20])
def test_stores_are_sealed_the_same_on_any_number_of_threads(
    tmp_path: Path, buffer_points: int
) -> None:
    # a dense tile among sparse ones: tiles are sealed at the same time, the dense one on
    # several threads, each written at its place in the files
    dense = _cloud(4_000, seed=7, extent=0.7)
    cloud = PointCloud.concatenate([_cloud(2_000, seed=8), dense])
    grid = TileGrid.square(1.5)
    names = ("points.npy", "order.npy", "offsets.npy", "starts.npy", "keys.npy")
    files = []
    for n_threads in (1, 3):
        with thread_limit(n_threads):
            folder = tmp_path / f"threads{n_threads}"
            chunks = _chunks(cloud, 700)
            build_tile_store(chunks, folder, grid=grid, buffer_points=buffer_points)
            files.append([(folder / name).read_bytes() for name in names])
            with TemporaryTileStore(chunks, grid=grid, buffer_points=1 << 20) as memory:
                assert memory.directory is None
                stored = TileStore(folder)
                for tile in stored.tiles:
                    a, b = memory.read(tile, halo_m=0.4), stored.read(tile, halo_m=0.4)
                    assert a.core.cloud.equals(b.core.cloud) and a.halo.cloud.equals(b.halo.cloud)
                    np.testing.assert_array_equal(a.core.indices, b.core.indices)
                    np.testing.assert_array_equal(a.halo.indices, b.halo.indices)
    assert files[0] == files[1]
    stored = TileStore(tmp_path / "threads3")
    assert sum(stored.count(tile) for tile in stored.tiles) == cloud.n_points


def test_sealing_a_spilled_tile_holds_its_codes_and_order_not_its_records(
    tmp_path: Path,
) -> None:
    """The densest tile of a station holds over half of its points: sealing it holds 6
    bytes a point and a window of records, not the tile's 40-byte records (with the sort's
    8-byte cells and destinations, 60 bytes a point of the tile)."""
    n = 1_000_000
    cloud = _cloud(n, extent=1.0)  # one tile
    writer = TemporaryTileStore.writer(
        grid=TileGrid.square(4.0, origin_xy=(-2.0, -2.0)), workdir=tmp_path, buffer_points=1 << 17
    )
    for chunk in _chunks(cloud, 1 << 16):
        writer.add(chunk)
    assert writer.spilled_points > n // 2
    tracemalloc.start()
    try:
        store = writer.close()
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    window = store_module._SEAL_WINDOW * 40
    assert peak < 6 * n + window + (2 << 20), f"{peak / 2**20:.1f} MiB while sealing"
    with TemporaryTileStore.adopt(store) as sealed:
        assert sealed.count(sealed.tiles[0]) == n
        np.testing.assert_array_equal(sealed.read_core(sealed.tiles[0]).indices, np.arange(n))


def test_sparse_tiles_far_apart(tmp_path: Path) -> None:
    """Two clusters 10 km apart in 1 m tiles: tile ids are renumbered, not allocated densely."""
    near, far = _cloud(200, seed=1), _cloud(200, seed=2)
    far = PointCloud(
        far.xyz + np.array([10_000.0, 10_000.0, 0.0]), far.intensity, far.rgb, far.labels
    )
    store = build_tile_store(
        [PointCloud.concatenate([near, far])], tmp_path / "s", grid=TileGrid.square(1.0)
    )
    assert len(store.tiles) == 72
    assert sum(store.count(tile) for tile in store.tiles) == 400


def test_a_store_and_its_jobs_travel_to_another_process(tmp_path: Path) -> None:
    cloud = _cloud(2_000)
    store = build_tile_store([cloud], tmp_path / "s", grid=TileGrid.square(1.0))
    assert len(pickle.dumps(store)) < 500
    again = pickle.loads(pickle.dumps(store))
    assert again.tiles == store.tiles
    jobs = store.jobs(halo_m=0.25)
    assert len(jobs) == len(store.tiles)
    assert all(len(pickle.dumps(job)) < 300 for job in jobs)
    # a fresh interpreter, as on a cluster's worker: a fork of this threaded process could
    # stall on a lock that one of its other threads held at the fork
    spawn = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=1, mp_context=spawn) as pool:
        remote = list(pool.map(_core_and_halo_sizes, jobs[:4]))
    local = [_core_and_halo_sizes(job) for job in jobs[:4]]
    assert remote == local
    assert all(core > 0 and halo > 0 for core, halo in remote)


def _core_and_halo_sizes(job: TileJob) -> tuple[int, int]:
    data = job.read()
    assert data.bounds == job.bounds
    return data.core.n_points, data.halo.n_points


def test_existing_folders_are_kept_unless_overwrite(tmp_path: Path) -> None:
    target = tmp_path / "s"
    target.mkdir()
    (target / "keep.txt").write_text("user data")
    with pytest.raises(FileExistsError, match="expected a new folder"):
        build_tile_store([_cloud(10)], target, grid=TileGrid.square(1.0))
    assert (target / "keep.txt").read_text() == "user data"
    store = build_tile_store([_cloud(10)], target, grid=TileGrid.square(1.0), overwrite=True)
    assert store.n_points == 10 and not (target / "keep.txt").exists()


def test_an_error_mid_stream_leaves_nothing(tmp_path: Path) -> None:
    def chunks():
        yield _cloud(100)
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        build_tile_store(chunks(), tmp_path / "s", grid=TileGrid.square(1.0), buffer_points=10)
    assert list(tmp_path.iterdir()) == []


def test_bad_input_is_refused(tmp_path: Path) -> None:
    grid = TileGrid.square(1.0)
    with pytest.raises(ShapeError, match="expected labels on every chunk or on none"):
        build_tile_store([_cloud(10), _cloud(10, labels=False)], tmp_path / "a", grid=grid)
    bad = _cloud(10)
    bad.xyz[3, 0] = np.nan
    with pytest.raises(ShapeError, match="expected finite coordinates"):
        build_tile_store([bad], tmp_path / "b", grid=grid)
    far = _cloud(10)
    far.xyz[3, 1] = 1e12  # 2**31 tiles of 1 m apart: more than a chunk's tiles can number
    with pytest.raises(ShapeError, match="expected points within 2147483648 tiles"):
        build_tile_store([far], tmp_path / "d", grid=grid)
    with pytest.raises(ShapeError, match="cell_size_m: expected a positive size"):
        TileGrid.square(0.0)
    store = build_tile_store([_cloud(10)], tmp_path / "c", grid=grid)
    with pytest.raises(ShapeError, match="halo_m: expected a finite width"):
        store.read_halo(store.tiles[0], -1.0)
    assert not any((tmp_path / name).exists() for name in "abd")


def test_damaged_stores_are_refused(tmp_path: Path) -> None:
    with pytest.raises(DataFormatError, match=r"expected a tile store holding tiles\.json"):
        TileStore(tmp_path)
    build_tile_store([_cloud(50)], tmp_path / "s", grid=TileGrid.square(1.0))
    manifest = tmp_path / "s" / "tiles.json"
    manifest.write_text(manifest.read_text().replace('"version": 1', '"version": 99'))
    with pytest.raises(DataFormatError, match="expected tile store version 1, found 99"):
        TileStore(tmp_path / "s")


def test_empty_scans_make_empty_stores(tmp_path: Path) -> None:
    store = build_tile_store([], tmp_path / "s", grid=TileGrid.square(1.0))
    assert store.n_points == 0 and store.tiles == ()


def test_temporary_store_is_in_memory_when_small_and_removed_on_exit(tmp_path: Path) -> None:
    cloud = _cloud(300)
    grid = TileGrid.square(1.0)
    with TemporaryTileStore([cloud], grid=grid, workdir=tmp_path) as small:
        assert small.directory is None
        with pytest.raises(TypeError, match="stays in its process"):
            pickle.dumps(small)
    assert list(tmp_path.iterdir()) == []
    spilled = TemporaryTileStore(_chunks(cloud, 50), grid=grid, workdir=tmp_path, buffer_points=60)
    with spilled as large:
        folder = large.directory
        assert folder is not None and folder.is_dir() and spilled.spilled_points > 0
        for tile in small.tiles:
            assert large.read(tile, halo_m=0.3).halo.cloud.equals(
                small.read(tile, halo_m=0.3).halo.cloud
            )
    assert not folder.exists()


def test_cache_tiles_are_built_once_and_rebuilt_when_the_cache_changes(tmp_path: Path) -> None:
    cache = tmp_path / "scan.cache"
    write_cache(cache, [_cloud(1_000)])
    calls: list[int] = []
    first = open_cache_tiles(cache, tile_size_m=1.0, progress=calls.append)
    assert first.n_points == 1_000 and calls[-1] == 1_000
    stamp = (first.directory / "tiles.json").stat().st_mtime_ns
    again = open_cache_tiles(cache, tile_size_m=1.0)
    assert (again.directory / "tiles.json").stat().st_mtime_ns == stamp  # reused
    write_cache(cache.with_name("other.cache"), [_cloud(500, seed=9)])
    for name in ("meta.json", "xyz.npy", "intensity.npy", "rgb.npy", "labels.npy"):
        (cache / name).write_bytes((cache.with_name("other.cache") / name).read_bytes())
    assert open_cache_tiles(cache, tile_size_m=1.0).n_points == 500


@settings(max_examples=25, deadline=None)
@given(
    n=st.integers(1, 300),
    chunk=st.integers(1, 80),
    tile=st.floats(0.05, 5.0),
    halo=st.floats(0.0, 3.0),
    subdivisions=st.integers(1, 9),
)
def test_round_trip_and_halos_for_any_grid(
    tmp_path_factory: pytest.TempPathFactory,
    n: int,
    chunk: int,
    tile: float,
    halo: float,
    subdivisions: int,
) -> None:
    cloud = _cloud(n, seed=n, extent=2.0)
    grid = TileGrid.square(tile)
    folder = tmp_path_factory.mktemp("store") / "s"
    store = build_tile_store(
        _chunks(cloud, chunk), folder, grid=grid, subdivisions=subdivisions, buffer_points=50
    )
    cores = [store.read_core(t) for t in store.tiles]
    indices = np.concatenate([c.indices for c in cores])
    np.testing.assert_array_equal(np.sort(indices), np.arange(n))
    assert PointCloud.concatenate([c.cloud for c in cores]).equals(cloud[indices])
    probe = store.tiles[len(store.tiles) // 2]
    assert set(store.read_halo(probe, halo).indices.tolist()) == _brute_halo(
        cloud, grid, probe, halo
    )


@pytest.mark.parametrize("buffer_points", [10, 1 << 20])
def test_kept_points_only_with_their_scan_positions(tmp_path: Path, buffer_points: int) -> None:
    cloud = _cloud(2_000)
    keep = np.asarray(cloud.labels) % 3 != 0
    keep[:50] = True  # one chunk keeps everything
    with TemporaryTileStore.writer(grid=TileGrid.square(1.0), buffer_points=buffer_points) as w:
        for start in range(0, 2_000, 50):
            w.add(cloud[start : start + 50], keep=keep[start : start + 50])
        w.add(cloud[:0], keep=keep[:0])
        with TemporaryTileStore.adopt(w.close()) as store:
            assert store.n_points == int(keep.sum())
            got = np.concatenate([store.read_core(t).indices for t in store.tiles])
            np.testing.assert_array_equal(np.sort(got), np.flatnonzero(keep))
            for tile in store.tiles:
                core = store.read_core(tile)
                assert core.cloud.equals(cloud[core.indices])


def _in_a_fresh_process(function: str, folder: Path, remap_bytes: int) -> dict[str, int]:
    """``function(folder, remap_bytes)`` of this module run in a new interpreter (the kernel
    writes smaps for every mapping of the process on every read, and a test worker that
    has loaded torch and numba has thousands)."""
    import json
    import subprocess
    import sys

    code = (
        f"import json; from tests.spatial.test_store import {function}; "
        f"print(json.dumps({function}({str(folder)!r}, {remap_bytes})))"
    )
    done = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=Path(__file__).resolve().parents[2],
    )
    assert done.returncode == 0, done.stderr
    found: dict[str, int] = json.loads(done.stdout.strip().splitlines()[-1])
    return found


def _mapped_while_reading_every_tile(folder: str, remap_bytes: int) -> dict[str, int]:
    """Build a 400 k-point store in ``folder`` and read every tile, maps reopened every
    ``remap_bytes``: the store file's resident KiB after sealing and at worst while reading."""
    import semantic3d.spatial.store as store_module

    store_module.REMAP_BYTES = remap_bytes
    cloud = _cloud(400_000, extent=40.0)
    grid = TileGrid(origin_xy=(-40.0, -40.0), cell_size_m=4.0)
    store = build_tile_store(
        _chunks(cloud, 50_000), Path(folder) / "s", grid=grid, buffer_points=20_000
    )
    points_file = Path(folder) / "s" / "points.npy"
    sealed = mapped_kib(points_file)
    seen, worst = 0, 0
    for tile in store.tiles:
        data = store.read(tile, halo_m=1.0)
        seen += data.core.cloud.n_points
        del data
        worst = max(worst, mapped_kib(points_file))
    return {
        "sealed_kib": sealed,
        "worst_kib": worst,
        "file_bytes": points_file.stat().st_size,
        "seen": seen,
        "points": cloud.n_points,
    }


@pytest.mark.skipif(not Path("/proc/self/smaps").is_file(), reason="needs Linux's smaps")
def test_reading_every_tile_keeps_the_mapped_store_out_of_resident_memory(tmp_path: Path) -> None:
    """Sealing writes the files without mapping them, and reading maps them anew every
    REMAP_BYTES: the store's pages do not pile up in the process's memory as tiles are read
    (they did: the whole store stayed resident, so memory grew with the scan).

    Measured in a fresh process: the kernel writes smaps for every mapping of the process
    on every read, and a test worker that has loaded torch and numba has thousands (40 s
    of this test's time in the suite against 8 s alone)."""
    found = _in_a_fresh_process("_mapped_while_reading_every_tile", tmp_path, 1 << 20)
    assert found["sealed_kib"] == 0  # written with plain writes
    assert found["file_bytes"] > 15 << 20
    assert found["seen"] == found["points"]
    assert found["worst_kib"] < 4 << 10  # KiB: the remap period and a tile, not the 16 MB store


def test_tiles_read_on_many_threads_while_the_maps_are_reopened(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Tiles of a folder store read on several threads at once, the maps reopened on every
    read (a scan's tasks read cores and halos at the same time, and the maps are reopened
    after every 128 MiB read): every read gets its points, none a map taken from under it."""
    import threading

    import semantic3d.spatial.store as store_module

    cloud = _cloud(5_000)
    store = build_tile_store(_chunks(cloud, 3000), tmp_path / "store", grid=TileGrid.square(1.0))
    monkeypatch.setattr(store_module, "REMAP_BYTES", 1)
    expected = {tile: cloud[store.read_core(tile).indices] for tile in store.tiles}
    failures: list[BaseException] = []
    start = threading.Barrier(4)

    def read() -> None:
        try:
            start.wait()
            for _ in range(40):
                for tile in store.tiles:
                    core = store.read_core(tile)
                    assert core.cloud.equals(expected[tile])
        except BaseException as exc:  # reported below
            failures.append(exc)

    threads = [threading.Thread(target=read) for _ in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert not failures, failures[0]


def test_a_tiles_core_comes_in_parts_in_scan_order(tmp_path: Path) -> None:
    cloud = _cloud(5_000)
    store = build_tile_store(_chunks(cloud, 700), tmp_path / "store", grid=TileGrid.square(2.0))
    for part_points in (1, 7, 100, 10_000):
        for tile in store.tiles:
            parts = list(store.iter_core_parts(tile, part_points))
            assert all(part.n_points == part_points for part in parts[:-1])
            assert 0 < parts[-1].n_points <= part_points
            whole = store.read_core(tile)
            np.testing.assert_array_equal(
                np.concatenate([part.indices for part in parts]), whole.indices
            )
            assert PointCloud.concatenate([part.cloud for part in parts]).equals(whole.cloud)
    assert list(store.iter_core_parts((99, 99), 10)) == []
    with pytest.raises(ShapeError, match="part_points: expected at least 1, found 0"):
        next(store.iter_core_parts(store.tiles[0], 0))


def _mapped_after_a_large_tile(folder: str, remap_bytes: int) -> dict[str, int]:
    """A store whose one tile holds 400 k points (16 MB), maps reopened every
    ``remap_bytes``: the store file's resident KiB after the tile was read whole and let
    go of, and at worst while it was read in parts."""
    import semantic3d.spatial.store as store_module

    store_module.REMAP_BYTES = remap_bytes
    cloud = _cloud(400_000, extent=0.9)
    grid = TileGrid(origin_xy=(-1.0, -1.0), cell_size_m=2.0)
    store = build_tile_store(_chunks(cloud, 50_000), Path(folder) / "s", grid=grid)
    points_file = Path(folder) / "s" / "points.npy"
    (tile,) = store.tiles
    core = store.read_core(tile).copied()
    read_whole = mapped_kib(points_file)
    del core
    after_whole = mapped_kib(points_file)
    worst_parts = 0
    for part in store.iter_core_parts(tile, 10_000):
        part.copied()
        worst_parts = max(worst_parts, mapped_kib(points_file))
    return {
        "file_kib": points_file.stat().st_size >> 10,
        "read_whole": read_whole,
        "after_whole": after_whole,
        "worst_parts": worst_parts,
    }


@pytest.mark.skipif(not Path("/proc/self/smaps").is_file(), reason="needs Linux's smaps")
def test_a_tile_larger_than_the_remap_period_is_let_go_of_with_its_points(tmp_path: Path) -> None:
    """A read of more than REMAP_BYTES gets maps of its own: once its points are let go
    of, none of the tile's pages stays in the process's memory (the store's kept maps
    held the densest tile's gigabyte until the next read); read in parts, a tile holds
    about the remap period. In a fresh process, as the test above."""
    found = _in_a_fresh_process("_mapped_after_a_large_tile", tmp_path, 1 << 20)
    assert found["file_kib"] > 15 << 10
    assert found["read_whole"] > 15 << 10  # the whole tile was read through a map
    assert found["after_whole"] == 0
    assert found["worst_parts"] < 6 << 10  # KiB: about the 1 MiB period, not the 16 MB tile
