"""Squares inside a tile: Morton codes of whole cells, and the quadtree cut of a tile's
points into squares of at most a given count."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from semantic3d.core.errors import ShapeError
from semantic3d.spatial.grid import MAX_CELL_DEPTH, TileGrid, quadtree_leaves


def _reference_codes(grid: TileGrid, xyz: np.ndarray, depth: int) -> np.ndarray:
    """The codes by numpy: each point's cell in its tile, its square, bits interleaved."""
    cells = np.floor((xyz[:, :2] - np.asarray(grid.origin_xy)) / grid.cell_size_m)
    local = cells.astype(np.int64) % grid.cells_per_tile  # numpy's % floors like Python
    square = local * (1 << depth) // grid.cells_per_tile
    codes = np.zeros(xyz.shape[0], np.int64)
    for bit in range(depth):
        codes |= ((square[:, 0] >> bit) & 1) << (2 * bit + 1)
        codes |= ((square[:, 1] >> bit) & 1) << (2 * bit)
    return codes


@settings(max_examples=60, deadline=None)
@given(
    xyz=arrays(
        np.float64,
        st.tuples(st.integers(0, 60), st.just(3)),
        elements=st.floats(-50.0, 50.0, allow_nan=False),
    ),
    origin=st.tuples(st.floats(-5.0, 5.0), st.floats(-5.0, 5.0)),
    cell=st.sampled_from([0.1, 0.25, 0.7, 1.0]),
    cells_per_tile=st.integers(1, 70),
    depth=st.integers(0, MAX_CELL_DEPTH),
)
def test_cell_codes_match_numpy(
    xyz: np.ndarray,
    origin: tuple[float, float],
    cell: float,
    cells_per_tile: int,
    depth: int,
) -> None:
    grid = TileGrid(origin_xy=origin, cell_size_m=cell, cells_per_tile=cells_per_tile)
    codes = grid.cell_codes(xyz, depth=depth)
    assert codes.dtype == np.uint16
    np.testing.assert_array_equal(codes, _reference_codes(grid, xyz, depth))
    assert np.all(codes < 4**depth)


def test_points_of_one_cell_share_a_code_and_quadrants_share_their_top_bits() -> None:
    grid = TileGrid(origin_xy=(0.0, 0.0), cell_size_m=1.0, cells_per_tile=8)
    # two points in each cell of tile (0, 0) and of tile (-1, 2)
    centres = np.array([(x + 0.5, y + 0.5, 0.0) for x in range(8) for y in range(8)])
    for shift in ([0.0, 0.0, 0.0], [-8.0, 16.0, 0.0]):
        xyz = np.concatenate([centres + shift, centres + shift + [0.4, -0.4, 3.0]])
        codes = grid.cell_codes(xyz, depth=3).astype(np.int64)
        np.testing.assert_array_equal(codes[:64], codes[64:])
        assert sorted(codes[:64].tolist()) == list(range(64))  # every square once
        quadrant = codes[:64] >> 4  # level 1: x half above y half
        expected = 2 * (centres[:, 0] >= 4) + (centres[:, 1] >= 4)
        np.testing.assert_array_equal(quadrant, expected)


def test_bad_depths_and_shapes_are_named() -> None:
    grid = TileGrid(origin_xy=(0.0, 0.0), cell_size_m=1.0, cells_per_tile=8)
    with pytest.raises(ShapeError, match=r"depth: expected 0\.\.8, found 9"):
        grid.cell_codes(np.zeros((1, 3)), depth=9)
    with pytest.raises(ShapeError, match=r"xyz: expected \(n, >=2\)"):
        grid.cell_codes(np.zeros(3), depth=2)
    with pytest.raises(ShapeError, match="max_count: expected a positive count, found 0"):
        quadtree_leaves(np.zeros(3, np.uint16), depth=2, max_count=0)
    with pytest.raises(ShapeError, match=r"codes: expected values in 0\.\.15 for depth 2"):
        quadtree_leaves(np.array([16]), depth=2, max_count=1)


@settings(max_examples=80, deadline=None)
@given(
    depth=st.integers(0, 4),
    max_count=st.integers(1, 40),
    data=st.data(),
)
def test_quadtree_leaves_are_the_squares_of_at_most_max_count(
    depth: int, max_count: int, data: st.DataObject
) -> None:
    n_codes = 4**depth
    codes = np.array(
        data.draw(st.lists(st.integers(0, n_codes - 1), max_size=200)), dtype=np.uint16
    )
    leaves = quadtree_leaves(codes, depth=depth, max_count=max_count)
    counts = np.bincount(codes, minlength=n_codes)
    squares: dict[int, int] = {}  # first code -> codes, by the definition, top down

    def cut(first: int, size: int) -> None:
        if size > 1 and counts[first : first + size].sum() > max_count:
            for k in range(4):
                cut(first + k * size // 4, size // 4)
        else:
            squares[first] = size

    cut(0, n_codes)
    expected = np.zeros(n_codes, np.int64)
    for first, size in squares.items():
        expected[first : first + size] = first
        assert counts[first : first + size].sum() <= max_count or size == 1
    np.testing.assert_array_equal(leaves, expected[codes])
    # the leaves do not depend on the points' order
    order = np.random.default_rng(depth).permutation(codes.size)
    np.testing.assert_array_equal(
        quadtree_leaves(codes[order], depth=depth, max_count=max_count), leaves[order]
    )
