"""The voxel pyramid: centroids, nesting, the point -> voxel map, bad inputs."""

from __future__ import annotations

import numpy as np
import pytest

from semantic3d.core.errors import ShapeError
from semantic3d.features.pyramid import ExtentError, build_pyramid, grid_origin


def _cloud(n: int = 3000, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.uniform(0, 4, (n, 3)) + np.array([870000.0, 6617000.0, 100.0])


def test_level_zero_holds_the_centroid_of_every_occupied_voxel() -> None:
    xyz = _cloud()
    origin = grid_origin(xyz[0], coarsest_voxel_size_m=0.8)
    pyramid = build_pyramid(xyz, base_voxel_size_m=0.1, n_levels=4, origin=origin)
    cells = np.floor((xyz - origin) / 0.1).astype(np.int64)
    unique, inverse = np.unique(cells, axis=0, return_inverse=True)
    level = pyramid.levels[0]
    assert level.n_voxels == len(unique)
    for voxel in range(0, len(unique), 97):
        members = xyz[inverse.ravel() == voxel]
        row = np.flatnonzero((level.cells == unique[voxel]).all(axis=1))[0]
        np.testing.assert_allclose(level.xyz[row] + origin, members.mean(axis=0), atol=1e-9)
    # every point maps to the voxel holding it
    np.testing.assert_array_equal(level.cells[pyramid.point_voxel], cells)


def test_coarser_levels_average_their_children_and_nest() -> None:
    xyz = _cloud(seed=1)
    origin = grid_origin(xyz[0], coarsest_voxel_size_m=0.8)
    pyramid = build_pyramid(xyz, base_voxel_size_m=0.1, n_levels=4, origin=origin)
    assert [lv.voxel_size_m for lv in pyramid.levels] == [0.1, 0.2, 0.4, 0.8]
    for lower, upper in zip(pyramid.levels[:-1], pyramid.levels[1:], strict=True):
        np.testing.assert_array_equal(upper.cells[lower.parent], lower.cells >> 1)
        assert np.all(np.diff(upper.keys) > 0)
        for parent in range(0, upper.n_voxels, 13):
            children = lower.xyz[lower.parent == parent]
            np.testing.assert_allclose(upper.xyz[parent], children.mean(axis=0), atol=1e-12)
    assert np.all(pyramid.levels[-1].parent == -1)
    np.testing.assert_array_equal(
        pyramid.ancestors(2), pyramid.levels[1].parent[pyramid.levels[0].parent]
    )


def test_attributes_are_averaged_like_coordinates() -> None:
    xyz = np.array([[0.01, 0.01, 0.01], [0.02, 0.02, 0.02], [0.5, 0.5, 0.5]])
    pyramid = build_pyramid(
        xyz,
        base_voxel_size_m=0.1,
        n_levels=2,
        origin=np.zeros(3),
        attributes=np.array([[10.0], [20.0], [60.0]]),
    )
    np.testing.assert_allclose(pyramid.levels[0].attributes[:, 0], [15.0, 60.0])
    np.testing.assert_allclose(pyramid.levels[1].attributes[:, 0], [15.0, 60.0])


def test_pyramid_of_a_subset_of_whole_voxels_is_bitwise_equal() -> None:
    xyz = _cloud(seed=2)
    origin = grid_origin(xyz[0], coarsest_voxel_size_m=0.8)
    whole = build_pyramid(xyz, base_voxel_size_m=0.1, n_levels=4, origin=origin)
    left = np.floor((xyz[:, 0] - origin[0]) / 0.8) == np.floor((xyz[0, 0] - origin[0]) / 0.8)
    part = build_pyramid(xyz[left], base_voxel_size_m=0.1, n_levels=4, origin=origin)
    for lw, lp in zip(whole.levels, part.levels, strict=True):
        rows = np.searchsorted(lw.keys, lp.keys)
        np.testing.assert_array_equal(lw.keys[rows], lp.keys)
        assert np.array_equal(lw.xyz[rows], lp.xyz)  # bit for bit


def test_points_too_far_from_the_origin_are_rejected() -> None:
    xyz = np.array([[0.0, 0.0, 0.0], [1e5, 0.0, 0.0]])
    with pytest.raises(
        ExtentError, match=r"reach 100000.0 m from the grid origin: expected at most"
    ):
        build_pyramid(xyz, base_voxel_size_m=0.025, n_levels=2, origin=np.zeros(3))


def test_bad_shapes_are_rejected() -> None:
    with pytest.raises(ShapeError, match=r"xyz: expected an \(n, 3\) array"):
        build_pyramid(np.zeros((4, 2)), base_voxel_size_m=0.1, n_levels=1, origin=np.zeros(3))
    with pytest.raises(ExtentError, match="finite"):
        grid_origin([np.nan, 0, 0], coarsest_voxel_size_m=1.0)
