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


def _rank(indices: np.ndarray) -> np.ndarray:
    """The reference rank: splitmix64 of the scan position, as a float in [0, 1)."""
    z = indices.astype(np.uint64) + np.uint64(0x9E3779B97F4A7C15)
    with np.errstate(over="ignore"):
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        z = z ^ (z >> np.uint64(31))
    return (z >> np.uint64(11)).astype(np.float64) / float(1 << 53)


def test_the_compiled_build_follows_the_sampling_rule(simulated_scan, tmp_path) -> None:
    """Each point stays in the first node on its path where rank * count < capacity.

    ``count`` is the number of scan points in the node's cube (leaf cells as integers).
    """
    lod = build_lod(simulated_scan.cache.path, tmp_path / "rule", capacity=NODE_CAPACITY)
    depth = lod.max_depth
    scale = (1 << depth) / lod.cube_size
    xyz = np.asarray(simulated_scan.cache.xyz)
    leaf = np.clip(np.floor((xyz - lod.cube_min) * scale).astype(np.int64), 0, (1 << depth) - 1)
    parent = {c: node.id for node in lod.nodes for c in node.children}
    local_min = lod.cube_min - lod.origin

    def cube_count(node) -> int:
        edge = lod.cube_size / (1 << node.depth)
        cell = np.round((np.array(node.bounds[:3]) - local_min) / edge).astype(np.int64)
        inside = (leaf >> (depth - node.depth)) == cell
        return int(inside.all(axis=1).sum())

    counts = {node.id: cube_count(node) for node in lod.nodes}
    for node in lod.nodes:
        ranks = _rank(lod.node_indices(node.id))
        if node.children:  # an internal node keeps exactly the points under its threshold
            assert (ranks * counts[node.id] < NODE_CAPACITY).all()
        ancestor = parent.get(node.id)
        while ancestor is not None:  # ...and every ancestor let them pass
            assert (ranks * counts[ancestor] >= NODE_CAPACITY).all()
            ancestor = parent.get(ancestor)
