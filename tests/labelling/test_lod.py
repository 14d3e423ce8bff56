"""The level-of-detail octree: every point in exactly one node, inside its node's cube."""

from __future__ import annotations

import json

import numpy as np
import pytest

from semantic3d.io.cache import open_cache
from semantic3d.labelling._lod_kernels import HASH_SALT
from semantic3d.labelling.lod import LOD_VERSION, build_lod, open_lod

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


@pytest.fixture(scope="module")
def clustered_cache(tmp_path_factory: pytest.TempPathFactory):
    """A sparse spread over 200 m, a dense cluster in a 2 cm cube and exact duplicates.

    Georeferenced coordinates; the cluster and the duplicates hold 60 and 15 times the
    capacity used below, the dense levels' leaves (78 cm) hundreds of times over.
    """
    from semantic3d.core.pointcloud import PointCloud
    from semantic3d.io.cache import write_cache

    rng = np.random.default_rng(5)
    corner = np.array([541_200.0, 4_182_300.0, 52.0])
    sparse = corner + rng.uniform(0.0, 200.0, (40_000, 3))
    cluster = corner + 73.31 + rng.uniform(0.0, 0.02, (60_000, 3))
    duplicates = np.tile(corner + np.array([12.5, 150.25, 3.0]), (15_000, 1))
    xyz = np.concatenate([sparse, cluster, duplicates])[rng.permutation(115_000)]
    n = len(xyz)
    cloud = PointCloud(
        xyz,
        rng.integers(-2000, 2000, n).astype(np.int32),
        rng.integers(0, 255, (n, 3)).astype(np.uint8),
    )
    path = tmp_path_factory.mktemp("clustered") / "clustered.cache"
    write_cache(path, [cloud])
    return path


def _paths(xyz: np.ndarray, lod) -> np.ndarray:
    """Each point's octant at every depth 1..max_depth (the digits of node names).

    Down to the position depth, the octant of its cell (cells of ``cube / 2**depth``);
    below it, 3 bits of a hash of its scan position (splitmix64 with the build's salt).
    """
    depth = lod.position_depth
    scale = float(1 << depth) / lod.cube_size
    cells = np.clip(np.floor((xyz - lod.cube_min) * scale).astype(np.int64), 0, (1 << depth) - 1)
    digits = np.zeros((len(xyz), lod.max_depth), np.uint8)
    for d in range(1, min(depth, lod.max_depth) + 1):
        bits = (cells >> (depth - d)) & 1
        digits[:, d - 1] = bits[:, 0] << 2 | bits[:, 1] << 1 | bits[:, 2]
    z = np.arange(len(xyz), dtype=np.uint64) + np.uint64(HASH_SALT)
    with np.errstate(over="ignore"):
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        z = z ^ (z >> np.uint64(31))
    for d in range(depth + 1, lod.max_depth + 1):
        digits[:, d - 1] = (z >> np.uint64(3 * (d - depth - 1))) & np.uint64(7)
    return digits


def test_dense_clusters_are_split_until_no_node_is_over_capacity(clustered_cache, tmp_path):
    """Deeper levels where points are dense, hash splits for duplicates: no leaf holds more
    than the capacity, every point is in exactly one node on its path, the sampling rule
    holds at every depth, whatever the chunking."""
    capacity = 1000
    stages: list[str] = []
    lod = build_lod(
        clustered_cache,
        tmp_path / "lod",
        capacity=capacity,
        progress=lambda stage, done, total: stages.append(stage) if done == total else None,
    )
    assert 1 <= stages.count("refine") <= 6, stages  # a few passes, not one per level
    n = lod.n_points
    # Leaves hold at most the capacity; a coarser node a random subsample of about it (a
    # binomial count of mean <= capacity: within 5 standard deviations).
    assert max(node.count for node in lod.nodes if not node.children) <= capacity
    assert max(node.count for node in lod.nodes) <= capacity + 5 * capacity**0.5
    seen = np.concatenate([lod.node_indices(node.id) for node in lod.nodes])
    np.testing.assert_array_equal(np.sort(seen), np.arange(n))
    assert lod.max_depth > lod.position_depth > lod.dense_depth  # space, then hash splits
    depths = [node.depth for node in lod.nodes]
    assert depths == sorted(depths)

    xyz = np.asarray(open_cache(clustered_cache).xyz)
    paths = _paths(xyz, lod)
    through = {b"": n}  # points whose path passes through each node (by its digits)
    group = np.zeros(n, np.int64)  # each point's path prefix, numbered
    for d in range(1, lod.max_depth + 1):
        _, first, group, counts = np.unique(
            group * 8 + paths[:, d - 1], return_index=True, return_inverse=True, return_counts=True
        )
        through.update((paths[i, :d].tobytes(), int(c)) for i, c in zip(first, counts, strict=True))
    local_min = lod.cube_min - lod.origin
    for node in lod.nodes:
        digits = np.array([int(c) for c in node.name[1:]], np.uint8)
        indices = lod.node_indices(node.id)
        assert (paths[indices, : node.depth] == digits).all(), node.name  # on their path
        count = through[digits.tobytes()]
        low, high = np.array(node.bounds[:3]), np.array(node.bounds[3:])
        points = xyz[indices] - lod.origin
        assert ((points >= low - 1e-6) & (points <= high + 1e-6)).all(), node.name
        edge = lod.cube_size / (1 << min(node.depth, lod.position_depth))
        cell = (low - local_min) / edge
        assert np.allclose(high - low, edge) and np.allclose(cell, np.round(cell)), node.name
        ranks = _rank(indices)
        if node.children:  # an internal node keeps the points under its threshold
            assert count > capacity and (ranks * count < capacity).all(), node.name
        else:
            assert count <= capacity, node.name
        for depth in range(node.depth):  # ...that every ancestor let pass
            assert (ranks * through[digits[:depth].tobytes()] >= capacity).all(), node.name
        for child in node.children:
            assert lod.nodes[child].depth == node.depth + 1
            assert lod.nodes[child].name[:-1] == node.name

    # Byte-identical files whatever the chunking.
    again = build_lod(clustered_cache, tmp_path / "again", capacity=capacity, chunk_size=7_000)
    for name in ("lod.json", "positions.npy", "rgb.npy", "intensity.npy", "index.npy"):
        assert (lod.directory / name).read_bytes() == (again.directory / name).read_bytes(), name


def test_a_level_of_detail_of_an_older_version_is_rebuilt(simulated_scan, tmp_path) -> None:
    cache = simulated_scan.cache.path
    directory = tmp_path / "lod"
    first = build_lod(cache, directory, capacity=NODE_CAPACITY)
    manifest = json.loads((directory / "lod.json").read_text())
    manifest["version"] = LOD_VERSION - 1
    (directory / "lod.json").write_text(json.dumps(manifest))
    first.close()
    stages: set[str] = set()
    rebuilt = open_lod(
        cache, directory=directory, capacity=NODE_CAPACITY,
        progress=lambda stage, done, total: stages.add(stage),
    )  # fmt: skip
    assert "write" in stages and rebuilt.n_points == simulated_scan.cache.n_points
    assert json.loads((directory / "lod.json").read_text())["version"] == LOD_VERSION
