"""A tile's voxels read strip by strip equal the whole block's, bit for bit, and every point
of the tile takes its voxel's label exactly once."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from semantic3d.baselines.randla.blocks import point_inputs, voxelise
from semantic3d.baselines.randla.config import InputConfig
from semantic3d.baselines.randla.model import grid_anchor, scan_grid
from semantic3d.baselines.randla.tile_voxels import core_point_labels, read_tile_voxels
from semantic3d.core import PointCloud
from semantic3d.spatial import build_tile_store
from tests.baselines.randla.conftest import tiny_config

VOXEL = 0.1


def _scene(seed: int) -> PointCloud:
    """A sparse spread, a dense cluster (a scanner's foot), points on the edges of tiles and
    voxels, duplicates, georeferenced coordinates."""
    rng = np.random.default_rng(seed)
    corner = np.array([652_103.0, 5_412_377.0, 230.0])
    sparse = corner + rng.uniform(0.0, 14.0, (3_000, 3)) * [1, 1, 0.3]
    dense = corner + np.array([6.1, 5.3, 0.0]) + rng.normal(0.0, 0.4, (20_000, 3))
    edges = corner + np.column_stack(
        [
            np.repeat(np.arange(0.0, 14.0, 0.1), 5),
            rng.uniform(0.0, 14.0, 700),
            rng.uniform(0.0, 3.0, 700),
        ]
    )
    xyz = np.concatenate([sparse, dense, edges, dense[:500]])
    xyz = xyz[rng.permutation(len(xyz))]
    return PointCloud.from_arrays(
        xyz,
        intensity=rng.integers(-2000, 2000, len(xyz)),
        rgb=rng.integers(0, 256, (len(xyz), 3)),
        labels=rng.integers(0, 9, len(xyz)),
    )


@pytest.mark.parametrize("strip_points", [500, 4_000, 1 << 20])
@pytest.mark.parametrize("halo_m", [0.0, 1.0, 2.5])
def test_strips_give_the_whole_blocks_voxels_and_labels(
    tmp_path: Path, strip_points: int, halo_m: float
) -> None:
    cloud = _scene(3)
    config = tiny_config()
    grid = scan_grid(np.asarray(cloud.xyz[0]), config)
    chunks = [cloud[i : i + 5_000] for i in range(0, cloud.n_points, 5_000)]
    store = build_tile_store(chunks, tmp_path / "store", grid=grid, buffer_points=8_000)
    origin = grid_anchor(grid)
    inputs = InputConfig(intensity=True, rgb=True)
    labelled = np.zeros(cloud.n_points, np.int64)
    for tile in store.tiles:
        # the whole block, as label_tile read it before: core then halo, voxelised at once
        data = store.read(tile, halo_m=halo_m)
        whole = PointCloud.concatenate([data.core.cloud, data.halo.cloud])
        expected = voxelise(
            np.asarray(whole.xyz), origin=origin, voxel_size_m=VOXEL,
            inputs=point_inputs(whole, inputs), labels=np.asarray(whole.labels),
        )  # fmt: skip
        in_core = np.zeros(expected.n_voxels, np.bool_)
        in_core[expected.inverse[: data.core.n_points]] = True

        held = read_tile_voxels(
            store, tile, halo_m=halo_m, origin=origin, voxel_size_m=VOXEL, inputs=inputs,
            labels=True, strip_points=strip_points,
        )  # fmt: skip
        assert np.array_equal(held.voxels.xyz, expected.xyz)  # the same sums: bit for bit
        assert np.array_equal(held.voxels.cells, expected.cells)
        assert np.array_equal(held.voxels.inputs, expected.inputs)
        assert np.array_equal(held.core, in_core)
        assert np.array_equal(held.voxels.labels, expected.labels)  # training's votes
        assert np.all(np.diff(held.keys) > 0)

        voxel_labels = np.random.default_rng(7).integers(1, 9, expected.n_voxels).astype(np.uint8)
        indices, labels = core_point_labels(
            store, tile, held, voxel_labels, origin=origin, voxel_size_m=VOXEL,
            strip_points=strip_points,
        )  # fmt: skip
        order = np.argsort(indices)
        core_order = np.argsort(data.core.indices)
        assert np.array_equal(indices[order], np.asarray(data.core.indices)[core_order])
        want = voxel_labels[expected.inverse[: data.core.n_points]]
        assert np.array_equal(labels[order], want[core_order])
        labelled[indices] += 1
    assert np.all(labelled == 1)  # every point of the scan once, by its tile


def test_a_dense_tile_is_read_in_strips_of_about_strip_points(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Memory follows the voxels: no read holds much more than a strip's points."""
    from semantic3d.spatial.store import TileStore

    cloud = _scene(4)
    grid = scan_grid(np.asarray(cloud.xyz[0]), tiny_config())
    store = build_tile_store([cloud], tmp_path / "store", grid=grid)
    largest = 0
    read_box_parts = TileStore.read_box_parts

    def counting(self: TileStore, box: object, **kwargs: object) -> object:
        nonlocal largest
        parts = list(read_box_parts(self, box, **kwargs))  # type: ignore[arg-type]
        largest = max(largest, sum(p.n_points for _, p in parts))
        return iter(parts)

    monkeypatch.setattr(TileStore, "read_box_parts", counting)
    densest = max(store.tiles, key=store.count)
    assert store.count(densest) > 5_000
    read_tile_voxels(
        store, densest, halo_m=1.0, origin=grid_anchor(grid), voxel_size_m=VOXEL,
        inputs=InputConfig(), strip_points=1_000,
    )  # fmt: skip
    assert largest < 3_000  # a strip's points and a voxel column or two more, not the tile's
