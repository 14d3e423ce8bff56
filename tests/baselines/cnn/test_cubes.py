"""Cube generation against slow references: borders, empty neighbourhoods, georeferenced."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from semantic3d.baselines.cnn.cubes import build_occupancy, compute_corner_cells, fill_cubes
from semantic3d.core.errors import ShapeError

SIZE = 8


def reference_by_centres(
    points: np.ndarray, queries: np.ndarray, origin: np.ndarray, sizes: tuple[float, ...]
) -> np.ndarray:
    """The definition: a cube voxel is 1 when the scan voxel holding its centre holds a point."""
    offsets = np.stack(np.meshgrid(*[np.arange(SIZE)] * 3, indexing="ij"), -1).reshape(-1, 3)
    out = np.zeros((len(queries), len(sizes), SIZE, SIZE, SIZE), np.float32)
    for s, v in enumerate(sizes):
        occupied = {tuple(c) for c in np.floor((points - origin) / v).astype(np.int64)}
        for q, p in enumerate(queries):
            centres = p + (offsets - SIZE / 2 + 0.5) * v
            cells = np.floor((centres - origin) / v).astype(np.int64)
            hit = np.array([tuple(c) in occupied for c in cells])
            out[q, s] = hit.reshape(SIZE, SIZE, SIZE)
    return out


def reference_by_tree(
    points: np.ndarray, queries: np.ndarray, origin: np.ndarray, sizes: tuple[float, ...]
) -> np.ndarray:
    """Neighbours from a k-d tree marked one by one into each cube."""
    tree = cKDTree(points)
    corners = compute_corner_cells(queries, origin=origin, voxel_sizes_m=sizes, cube_voxels=SIZE)
    out = np.zeros((len(queries), len(sizes), SIZE, SIZE, SIZE), np.float32)
    for s, v in enumerate(sizes):
        near = tree.query_ball_point(queries, r=(SIZE / 2 + 1) * v, p=np.inf)
        for q, neighbours in enumerate(near):
            cells = np.floor((points[neighbours] - origin) / v).astype(np.int64) - corners[q, s]
            inside = np.all((cells >= 0) & (cells < SIZE), axis=1)
            for i, j, k in cells[inside]:
                out[q, s, i, j, k] = 1.0
    return out


def test_points_on_voxel_borders_follow_the_definition() -> None:
    # Powers of two: every coordinate below is exact, many lie on voxel borders and
    # half-voxel corners (where rounding to the nearest corner goes up).
    rng = np.random.default_rng(0)
    sizes = (0.125, 0.25, 0.5)
    origin = np.array([-4.0, -4.0, -2.0])
    points = rng.integers(-24, 24, (400, 3)) * 0.0625
    queries = np.concatenate([points[:30], rng.integers(-24, 24, (30, 3)) * 0.03125])
    occupancy = build_occupancy(points, origin=origin, voxel_sizes_m=sizes)
    corners = compute_corner_cells(queries, origin=origin, voxel_sizes_m=sizes, cube_voxels=SIZE)
    cubes = fill_cubes(occupancy, corners, cube_voxels=SIZE)
    np.testing.assert_array_equal(cubes, reference_by_centres(points, queries, origin, sizes))
    assert 0 < cubes.mean() < 1


def test_cubes_equal_a_kd_tree_reference_and_empty_neighbourhoods_are_zero() -> None:
    rng = np.random.default_rng(1)
    sizes = (0.025, 0.1, 0.4)
    points = np.round(rng.uniform(0, 6, (3000, 3)) * [1, 1, 0.3], 3)
    far = np.array([[60.0, 60.0, 0.0], [-40.0, 3.0, 9.0]])  # nothing within any cube
    queries = np.concatenate([points[::100], far])
    origin = np.zeros(3)
    occupancy = build_occupancy(points, origin=origin, voxel_sizes_m=sizes)
    corners = compute_corner_cells(queries, origin=origin, voxel_sizes_m=sizes, cube_voxels=SIZE)
    cubes = fill_cubes(occupancy, corners, cube_voxels=SIZE)
    np.testing.assert_array_equal(cubes, reference_by_tree(points, queries, origin, sizes))
    assert not cubes[-2:].any()
    assert cubes[:-2, :, SIZE // 2 - 1 : SIZE // 2 + 1, SIZE // 2 - 1 : SIZE // 2 + 1].any()
    empty = build_occupancy(np.empty((0, 3)), origin=origin, voxel_sizes_m=sizes)
    assert not fill_cubes(empty, corners, cube_voxels=SIZE).any()


def test_georeferenced_coordinates_give_the_cubes_of_the_same_scan_near_zero() -> None:
    rng = np.random.default_rng(2)
    sizes = (0.025, 0.05, 0.4)
    # Not whole millimetres: those lie exactly on 2.5 cm borders, where the shift's
    # rounding (1e-10 m) may pick the other voxel.
    local = rng.uniform(0, 5, (2000, 3)) * [1, 1, 0.2]
    shift = np.array([870_000.0, 6_617_000.0, 0.0])  # 0.4 m grid points, as the origin
    results = []
    for points, origin in ((local, np.zeros(3)), (local + shift, shift)):
        occupancy = build_occupancy(points, origin=origin, voxel_sizes_m=sizes)
        corners = compute_corner_cells(
            points[::50], origin=origin, voxel_sizes_m=sizes, cube_voxels=SIZE
        )
        results.append(fill_cubes(occupancy, corners, cube_voxels=SIZE))
    np.testing.assert_array_equal(results[0], results[1])
    # float32 coordinates at 1e6 m have a 6 cm step: the cubes would be wrong.
    coarse = (local + shift).astype(np.float32).astype(np.float64)
    occupancy = build_occupancy(coarse, origin=shift, voxel_sizes_m=sizes)
    corners = compute_corner_cells(
        coarse[::50], origin=shift, voxel_sizes_m=sizes, cube_voxels=SIZE
    )
    assert not np.array_equal(fill_cubes(occupancy, corners, cube_voxels=SIZE), results[0])


def test_torch_cubes_equal_the_compiled_ones() -> None:
    from semantic3d.baselines.cnn.cubes_torch import DeviceOccupancy

    rng = np.random.default_rng(3)
    sizes = (0.05, 0.2)
    points = rng.uniform(0, 3, (1500, 3))
    occupancy = build_occupancy(points, origin=np.zeros(3), voxel_sizes_m=sizes)
    corners = compute_corner_cells(
        points[::30], origin=np.zeros(3), voxel_sizes_m=sizes, cube_voxels=SIZE
    )
    device = DeviceOccupancy(occupancy, device="cpu", cube_voxels=SIZE)
    np.testing.assert_array_equal(
        device.fill(corners).numpy(), fill_cubes(occupancy, corners, cube_voxels=SIZE)
    )


def test_bad_shapes_are_refused() -> None:
    occupancy = build_occupancy(np.zeros((1, 3)), origin=np.zeros(3), voxel_sizes_m=(0.1, 0.2))
    with pytest.raises(ShapeError, match=r"corners: expected \(n, 2, 3\), found \(4, 3, 3\)"):
        fill_cubes(occupancy, np.zeros((4, 3, 3), np.int64), cube_voxels=SIZE)
    with pytest.raises(ShapeError, match=r"xyz: expected \(n, 3\) coordinates, found \(5, 2\)"):
        build_occupancy(np.zeros((5, 2)), origin=np.zeros(3), voxel_sizes_m=(0.1,))
