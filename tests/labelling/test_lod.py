"""The level-of-detail octree: every point in exactly one node, inside its node's cube."""

from __future__ import annotations

import numpy as np

from semantic3d.labelling.lod import build_lod, open_lod

from .conftest import NODE_CAPACITY


def test_every_point_is_in_exactly_one_node_inside_its_cube(simulated_scan, tmp_path) -> None:
    stages: set[str] = set()
    lod = build_lod(
        simulated_scan.cache.path,
        tmp_path / "lod",
        capacity=NODE_CAPACITY,
        progress=lambda stage, done, total: stages.add(stage),
    )
    assert stages == {"bounds", "histogram", "counts", "write"}
    n = simulated_scan.cache.n_points
    assert lod.n_points == n and len(lod.nodes) > 8
    seen = np.concatenate([lod.node_indices(node.id) for node in lod.nodes])
    assert seen.size == n
    np.testing.assert_array_equal(np.sort(seen), np.arange(n))
    xyz = np.asarray(simulated_scan.cache.xyz)
    for node in lod.nodes:
        points = lod.read_node(node.id)
        low, high = np.array(node.bounds[:3]), np.array(node.bounds[3:])
        assert ((points.positions >= low - 1e-3) & (points.positions <= high + 1e-3)).all()
        np.testing.assert_allclose(
            points.positions, xyz[points.indices] - lod.origin, atol=1e-4
        )  # float32 re-centred on the scan origin
        for child in node.children:
            assert lod.nodes[child].depth == node.depth + 1
            assert lod.nodes[child].name.startswith(node.name)
    # Coarse nodes are subsamples near the capacity; ids are breadth first.
    assert all(node.count <= NODE_CAPACITY * 1.5 for node in lod.nodes if node.children)
    depths = [node.depth for node in lod.nodes]
    assert depths == sorted(depths)


def test_build_does_not_depend_on_chunking_and_is_reused(simulated_scan, tmp_path) -> None:
    cache = simulated_scan.cache.path
    small = build_lod(cache, tmp_path / "small", capacity=NODE_CAPACITY, chunk_size=7_000)
    big = build_lod(cache, tmp_path / "big", capacity=NODE_CAPACITY)
    assert [n.to_dict() for n in small.nodes] == [n.to_dict() for n in big.nodes]
    for node in small.nodes:
        np.testing.assert_array_equal(small.node_indices(node.id), big.node_indices(node.id))
    first = open_lod(cache, capacity=NODE_CAPACITY)
    manifest = first.directory / "lod.json"
    stamp = manifest.stat().st_mtime_ns
    again = open_lod(cache, capacity=NODE_CAPACITY, progress=lambda *a: 1 / 0)  # no rebuild
    assert again.directory == first.directory and manifest.stat().st_mtime_ns == stamp
