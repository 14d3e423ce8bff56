"""Neighbour searches (the compiled k-d tree on the CPU, torch's on a GPU) against brute
force, and the levels built from them."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from semantic3d.baselines.randla.levels import build_levels, level_sizes, stack_levels
from semantic3d.baselines.randla.neighbours import knn_cpu, knn_torch
from semantic3d.core.errors import ShapeError


def _brute_force(points: np.ndarray, queries: np.ndarray, k: int) -> np.ndarray:
    squared = ((queries[:, None, :].astype(np.float64) - points[None, :, :]) ** 2).sum(axis=2)
    return np.sort(squared, axis=1)[:, :k]


def _distances(points: np.ndarray, queries: np.ndarray, indices: np.ndarray) -> np.ndarray:
    return ((points[indices].astype(np.float64) - queries[:, None, :]) ** 2).sum(axis=2)


@pytest.mark.parametrize("search", ["cpu", "torch"])
@pytest.mark.parametrize(("n", "k"), [(500, 16), (7, 16), (1, 3)])
def test_knn_equals_brute_force(search: str, n: int, k: int) -> None:
    rng = np.random.default_rng(n)
    points = rng.uniform(-10, 10, (n, 3)).astype(np.float32)
    queries = np.concatenate([points[:50], rng.uniform(-10, 10, (40, 3)).astype(np.float32)])
    if search == "cpu":
        found = knn_cpu(points, queries, k)
    else:
        found = knn_torch(torch.from_numpy(points), torch.from_numpy(queries), k).numpy()
    assert found.shape == (queries.shape[0], k) and found.dtype == np.int64
    k_eff = min(n, k)
    np.testing.assert_allclose(
        _distances(points, queries, found[:, :k_eff]),
        _brute_force(points, queries, k_eff),
        rtol=1e-4,
        atol=1e-4,
    )
    assert (found[:, k_eff:] == found[:, k_eff - 1 : k_eff]).all()  # the farthest repeats
    assert (found[: min(50, n), 0] == np.arange(min(50, n))).all()  # a point is its own nearest


def test_knn_among_no_point_is_refused() -> None:
    with pytest.raises(ShapeError, match="at least one"):
        knn_cpu(np.empty((0, 3), np.float32), np.zeros((2, 3), np.float32), 4)


def test_levels_are_prefixes_and_upsampling_finds_the_nearest_kept_point() -> None:
    assert level_sizes(1000, [4, 4, 2]) == (1000, 250, 63, 32)
    cloud = np.random.default_rng(0).uniform(-5, 5, (400, 3)).astype(np.float32)
    levels = build_levels(cloud, k=8, ratios=(4, 4), device="cpu")
    assert levels.sizes == (400, 100, 25)
    for level in range(2):
        here = cloud[: levels.sizes[level]]
        below = cloud[: levels.sizes[level + 1]]
        up = levels.up[level].numpy()
        assert (up[: levels.sizes[level + 1]] == np.arange(levels.sizes[level + 1])).all()
        nearest = _brute_force(below, here, 1)[:, 0]
        np.testing.assert_allclose(_distances(below, here, up[:, None])[:, 0], nearest, atol=1e-5)
    batch = stack_levels(
        [cloud, cloud[:40]],
        [levels, build_levels(cloud[:40], k=8, ratios=(4, 4), device="cpu")],
        device="cpu",
    )
    assert [t.shape[0] for t in batch.xyz] == [440, 110, 28]
    assert int(batch.neighbours[0][400:].min()) >= 400  # the second cloud's own points
    assert int(batch.up[0][400:].min()) >= 100 and int(batch.pool[1][-1]) == 100 + 2


@pytest.mark.gpu
def test_knn_on_the_gpu_equals_the_compiled_search() -> None:
    if not torch.cuda.is_available():
        pytest.skip("no CUDA device")
    points = np.random.default_rng(5).uniform(-20, 20, (20_000, 3)).astype(np.float32)
    on_gpu = knn_torch(torch.from_numpy(points).cuda(), torch.from_numpy(points).cuda(), 16)
    np.testing.assert_allclose(
        _distances(points, points, on_gpu.cpu().numpy()),
        _distances(points, points, knn_cpu(points, points, 16)),
        rtol=1e-3,
        atol=1e-4,
    )
