"""TileSpill: core + halo binning, identical whether buffered in memory or spilled."""

from __future__ import annotations

import numpy as np

from semantic3d.evaluation.tilespill import CORE, HALO, TileSpill


def _points(n: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(5)
    xyz = rng.uniform(-3.0, 3.0, (n, 3))
    return xyz, rng.integers(0, 9, n).astype(np.uint8)


def test_core_tiles_partition_and_halos_hold_points_near_edges() -> None:
    xyz, labels = _points(5_000)
    with TileSpill(tile_size_m=1.0, margin_m=0.1) as spill:
        spill.add(0, xyz, labels)
        tiles = list(spill.tiles())
        assert len(tiles) == 36
        cores = [spill.read(0, CORE, t) for t in tiles]
        assert sum(c.shape[0] for c in cores) == 5_000
        for (ix, iy), core in zip(tiles, cores, strict=True):
            assert np.all(np.floor(core[:, :2]) == [ix, iy])
            halo = spill.read(0, HALO, (ix, iy))
            # halo: outside the tile, within 0.1 m of it in x and y
            outside = (np.floor(halo[:, :2]) != [ix, iy]).any(axis=1)
            assert outside.all()
            assert np.all(halo[:, 0] >= ix - 0.1) and np.all(halo[:, 0] < ix + 1.1)
            assert np.all(halo[:, 1] >= iy - 0.1) and np.all(halo[:, 1] < iy + 1.1)
            # every point near the tile is in its core or halo
            near = (
                (xyz[:, 0] >= ix - 0.1)
                & (xyz[:, 0] < ix + 1.1)
                & (xyz[:, 1] >= iy - 0.1)
                & (xyz[:, 1] < iy + 1.1)
            )
            assert core.shape[0] + halo.shape[0] == int(near.sum())


def test_spilled_equals_buffered() -> None:
    xyz, labels = _points(3_000)
    with (
        TileSpill(tile_size_m=1.5, margin_m=0.2) as memory,
        TileSpill(tile_size_m=1.5, margin_m=0.2, buffer_points=100) as disk,
    ):
        for start in range(0, 3_000, 250):
            memory.add(1, xyz[start : start + 250], labels[start : start + 250])
            disk.add(1, xyz[start : start + 250], labels[start : start + 250])
        assert memory.spilled_points == 0 and disk.spilled_points > 0
        assert list(memory.tiles()) == list(disk.tiles())
        for tile in memory.tiles():
            for kind in (CORE, HALO):
                np.testing.assert_array_equal(memory.read(1, kind, tile), disk.read(1, kind, tile))
        assert disk.read(0, CORE, (0, 0)).shape == (0, 4)  # another cloud: nothing


def test_sparse_tiles_far_apart() -> None:
    """Two clusters 10 km apart in 1 m tiles: tile ids are renumbered, not allocated densely."""
    xyz = np.array([[0.5, 0.5, 0.0], [10_000.5, -10_000.5, 1.0], [0.6, 0.4, 2.0]])
    with TileSpill(tile_size_m=1.0, margin_m=0.05) as spill:
        spill.add(0, xyz, np.array([1, 2, 3], np.uint8))
        assert list(spill.tiles()) == [(0, 0), (10_000, -10_001)]
        np.testing.assert_array_equal(spill.read(0, CORE, (0, 0))[:, 3], [1, 3])
        np.testing.assert_array_equal(spill.read(0, CORE, (10_000, -10_001))[:, 3], [2])
