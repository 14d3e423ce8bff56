"""The voxel pyramid: centroids, nesting, the point -> voxel map, bad inputs."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from semantic3d.core.errors import ShapeError
from semantic3d.features.pyramid import (
    ExtentError,
    build_pyramid,
    build_pyramid_in_parts,
    grid_origin,
)


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


def _numpy_pyramid(
    xyz: np.ndarray, attributes: np.ndarray, size: float, n_levels: int, origin: np.ndarray
) -> list[tuple[np.ndarray, ...]]:
    """The pyramid as numpy builds it (a stable argsort of the keys per level, each voxel's
    mean summed in order): ``(cells, keys, xyz, attributes, parent)`` per level, and the
    point -> voxel map last."""
    from semantic3d.spatial.voxels import CELL_BITS, CELL_OFFSET

    def pack(cells: np.ndarray) -> np.ndarray:
        shifted = cells + CELL_OFFSET
        return (shifted[:, 0] << (2 * CELL_BITS)) | (shifted[:, 1] << CELL_BITS) | shifted[:, 2]

    def means(values: np.ndarray, order: np.ndarray, starts: np.ndarray) -> np.ndarray:
        out = np.empty((starts.size - 1, values.shape[1]))
        for group in range(starts.size - 1):
            for column in range(values.shape[1]):
                total = 0.0
                for i in order[starts[group] : starts[group + 1]]:
                    total += values[i, column]
                out[group, column] = total / (starts[group + 1] - starts[group])
        return out

    def group(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        order = np.argsort(keys, kind="stable")
        ordered = keys[order]
        change = np.flatnonzero(ordered[1:] != ordered[:-1]) + 1
        starts = np.concatenate(([0], change, [keys.size])).astype(np.int64)
        member = np.empty(keys.size, np.int64)
        member[order] = np.repeat(np.arange(starts.size - 1), np.diff(starts))
        return order, starts, member

    cells = np.floor((xyz - origin) / size).astype(np.int64)
    keys = pack(cells)
    order, starts, point_voxel = group(keys)
    level = (
        cells[order[starts[:-1]]],
        keys[order[starts[:-1]]],
        means(xyz - origin, order, starts),
        means(attributes, order, starts),
    )
    levels = []
    for number in range(n_levels):
        if number == n_levels - 1:
            levels.append((*level, np.full(level[1].size, -1)))
            break
        parent_cells = level[0] >> 1
        parent_keys = pack(parent_cells)
        order, starts, parent = group(parent_keys)
        levels.append((*level, parent))
        level = (
            parent_cells[order[starts[:-1]]],
            parent_keys[order[starts[:-1]]],
            means(level[2], order, starts),
            means(level[3], order, starts),
        )
    return [*levels, (point_voxel,)]


@pytest.mark.parametrize("threads", [1, 3])
@pytest.mark.parametrize("seed", [0, 1])
def test_the_pyramid_is_numpys_bit_for_bit_on_any_number_of_threads(
    seed: int, threads: int
) -> None:
    """Sorted by the parallel radix sort, each voxel summed on its thread: the same arrays
    as a stable argsort and sums in point order give."""
    from semantic3d.core.threads import thread_limit

    rng = np.random.default_rng(seed)
    xyz = _cloud(n=40_000, seed=seed)
    xyz[::7] = xyz[1::7]  # points sharing voxels, in any order
    xyz[5] = xyz[0] + [-3.0, 2.5, -1.0]  # cells below the first point's
    attributes = rng.random((xyz.shape[0], 2))
    origin = grid_origin(xyz[0], coarsest_voxel_size_m=0.8)
    with thread_limit(threads):
        pyramid = build_pyramid(
            xyz, base_voxel_size_m=0.05, n_levels=5, origin=origin, attributes=attributes
        )
    *expected, (point_voxel,) = _numpy_pyramid(xyz, attributes, 0.05, 5, origin)
    np.testing.assert_array_equal(pyramid.point_voxel, point_voxel)
    for level, (cells, keys, centres, values, parent) in zip(pyramid.levels, expected, strict=True):
        np.testing.assert_array_equal(level.cells, cells)
        np.testing.assert_array_equal(level.keys, keys)
        assert np.array_equal(level.xyz, centres)  # bit for bit
        assert np.array_equal(level.attributes, values)
        np.testing.assert_array_equal(level.parent, parent)


def test_a_coordinate_that_is_not_a_number_is_rejected() -> None:
    xyz = _cloud(n=10)
    xyz[3, 1] = np.nan
    with pytest.raises(ExtentError, match="finite coordinates"):
        build_pyramid(
            xyz,
            base_voxel_size_m=0.1,
            n_levels=2,
            origin=grid_origin(xyz[0], coarsest_voxel_size_m=0.2),
        )


def _assert_same_pyramid(got: object, expected: object) -> None:
    """Every array of two pyramids equal bit for bit (and of one dtype)."""
    assert np.array_equal(got.point_voxel, expected.point_voxel)  # type: ignore[attr-defined]
    for level, want in zip(got.levels, expected.levels, strict=True):  # type: ignore[attr-defined]
        assert level.voxel_size_m == want.voxel_size_m
        for name in ("cells", "keys", "xyz", "attributes", "parent"):
            a, b = getattr(level, name), getattr(want, name)
            assert a.dtype == b.dtype and a.shape == b.shape, name
            assert a.tobytes() == b.tobytes(), name  # bit for bit


@settings(max_examples=30, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(1, 6000),
    cuts=st.lists(st.floats(0.0, 1.0), max_size=6),
    with_attributes=st.booleans(),
    threads=st.sampled_from([1, 3]),
)
def test_a_pyramid_built_a_part_at_a_time_is_the_whole_builds_bit_for_bit(
    seed: int, n: int, cuts: list[float], with_attributes: bool, threads: int
) -> None:
    """Dense voxels (about 40 points each) cut across parts at any place, empty parts too:
    each voxel's sums run on in input order from part to part, so every value is the
    whole build's (sums restarted in each part and added would differ in the last bits)."""
    from semantic3d.core.threads import thread_limit

    rng = np.random.default_rng(seed)
    side = max(1, round((n / 40) ** (1 / 3)))  # voxels of 0.05 m along each axis
    # near the origin, every bit of a coordinate counts: sums round at every step
    xyz = rng.uniform(0, 0.05 * side, (n, 3)) + np.array([10.0, 20.0, 5.0])
    xyz[rng.random(n) < 0.1] *= 1.5  # some points far off in other voxels
    attributes = rng.random((n, 2)) * 255 if with_attributes else None
    origin = grid_origin(xyz[0], coarsest_voxel_size_m=0.8)
    bounds = sorted({0, n, *(round(c * n) for c in cuts)})
    with thread_limit(threads):
        whole = build_pyramid(
            xyz, base_voxel_size_m=0.05, n_levels=5, origin=origin, attributes=attributes
        )
        in_parts = build_pyramid_in_parts(
            (
                (xyz[a:b], None if attributes is None else attributes[a:b])
                for a, b in zip([0, *bounds], bounds, strict=False)
            ),
            n_points=n,
            base_voxel_size_m=0.05,
            n_levels=5,
            origin=origin,
            n_attributes=0 if attributes is None else 2,
        )
    _assert_same_pyramid(in_parts, whole)


def test_parts_of_another_size_or_shape_are_rejected() -> None:
    xyz = _cloud(n=100)
    origin = grid_origin(xyz[0], coarsest_voxel_size_m=0.8)

    def build(parts: list, n_points: int = 100, n_attributes: int = 0) -> object:
        return build_pyramid_in_parts(
            parts,
            n_points=n_points,
            base_voxel_size_m=0.05,
            n_levels=3,
            origin=origin,
            n_attributes=n_attributes,
        )

    with pytest.raises(ShapeError, match="expected 100 points, found 60"):
        build([(xyz[:60], None)])
    with pytest.raises(ShapeError, match="expected 50 points, found more"):
        build([(xyz[:40], None), (xyz[40:], None)], n_points=50)
    with pytest.raises(ShapeError, match=r"expected an \(n, 3\) part"):
        build([(xyz[:, :2], None)])
    with pytest.raises(ShapeError, match=r"attributes: expected \(100, 2\), found \(100, 1\)"):
        build([(xyz, np.zeros((100, 1)))], n_attributes=2)
