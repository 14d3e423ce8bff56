"""One-pass grid kernels: tile keys with their extent and the coordinates checked, and a
point's place (relative position, packed tile, square) against the numpy expressions."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from semantic3d.core.errors import ShapeError
from semantic3d.core.threads import thread_limit
from semantic3d.spatial.grid import MAX_CELL_DEPTH, TileGrid

_POINTS = arrays(
    np.float64,
    st.tuples(st.integers(1, 80), st.just(3)),
    elements=st.floats(-60.0, 60.0, allow_nan=False),
)
_GRIDS = st.builds(
    lambda x, y, cell, cells: TileGrid(origin_xy=(x, y), cell_size_m=cell, cells_per_tile=cells),
    st.floats(-5.0, 5.0),
    st.floats(-5.0, 5.0),
    st.sampled_from([0.1, 0.25, 0.7, 1.0]),
    st.integers(1, 70),
)


@settings(max_examples=60, deadline=None)
@given(xyz=_POINTS, grid=_GRIDS, data=st.data())
def test_keys_and_extent_equal_numpy(xyz: np.ndarray, grid: TileGrid, data: st.DataObject) -> None:
    keep = data.draw(arrays(np.bool_, xyz.shape[0]))
    for marks in (None, keep):
        keys, extent = grid.tile_keys_extent(xyz, keep=marks)
        np.testing.assert_array_equal(keys, grid.tile_keys(xyz))
        kept = keys if marks is None else keys[marks]
        if kept.shape[0] == 0:
            assert extent is None
        else:
            x, y = kept[:, 0], kept[:, 1]
            assert extent == (x.min(), x.max(), y.min(), y.max())


def test_the_extent_of_a_large_cloud_is_reduced_over_every_thread() -> None:
    grid = TileGrid.square(0.5)
    rng = np.random.default_rng(3)
    xyz = rng.normal(0.0, 20.0, (300_000, 3))
    keep = rng.random(xyz.shape[0]) < 0.3
    for n_threads in (1, 3):
        with thread_limit(n_threads):
            keys, extent = grid.tile_keys_extent(xyz, keep=keep)
        kept = keys[keep]
        assert extent == (kept[:, 0].min(), kept[:, 0].max(), kept[:, 1].min(), kept[:, 1].max())
        assert extent != (keys[:, 0].min(), keys[:, 0].max(), keys[:, 1].min(), keys[:, 1].max())


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_a_coordinate_that_is_not_a_number_is_named_with_its_row(bad: float) -> None:
    grid = TileGrid.square(1.0)
    xyz = np.zeros((100_000, 3))
    xyz[70_001, 1] = bad
    xyz[90_000, 0] = bad
    xyz[5, 2] = np.nan  # z is not binned
    for n_threads in (1, 3):
        with thread_limit(n_threads), pytest.raises(ShapeError) as caught:
            grid.tile_keys_extent(xyz)
        assert (
            str(caught.value)
            == f"xyz: expected finite coordinates, found [0.0, {bad}] at row 70001"
        )


@settings(max_examples=60, deadline=None)
@given(xyz=_POINTS, grid=_GRIDS, depth=st.integers(0, MAX_CELL_DEPTH), data=st.data())
def test_places_equal_their_numpy_expressions(
    xyz: np.ndarray, grid: TileGrid, depth: int, data: st.DataObject
) -> None:
    relative_to = np.array(data.draw(st.tuples(*[st.floats(-9.0, 9.0)] * 3)))
    n = xyz.shape[0]
    out = (np.empty((n, 3), np.float32), np.empty(n, np.int64), np.empty(n, np.uint16))
    grid.places(xyz, depth=depth, relative_to=relative_to, out=out)
    expected_relative = np.empty((n, 3), np.float32)
    np.subtract(xyz, relative_to, out=expected_relative, casting="same_kind")
    keys = grid.tile_keys(xyz)
    np.testing.assert_array_equal(out[0], expected_relative)
    np.testing.assert_array_equal(out[1], (keys[:, 0] << 32) + keys[:, 1])
    np.testing.assert_array_equal(out[2], grid.cell_codes(xyz, depth=depth))


def test_places_name_wrong_outputs() -> None:
    grid = TileGrid.square(1.0)
    xyz = np.zeros((4, 3))
    good = (np.empty((4, 3), np.float32), np.empty(4, np.int64), np.empty(4, np.uint16))
    for out in (
        (np.empty((4, 3), np.float64), *good[1:]),
        (good[0], np.empty(3, np.int64), good[2]),
        (*good[:2], np.empty(4, np.int64)),
    ):
        with pytest.raises(ShapeError, match=r"places: expected \(n, 3\) points and out float32"):
            grid.places(xyz, depth=2, relative_to=np.zeros(3), out=out)
    with pytest.raises(ShapeError, match=r"depth: expected 0\.\.8, found 9"):
        grid.places(xyz, depth=9, relative_to=np.zeros(3), out=good)
    with pytest.raises(ShapeError, match=r"places: expected \(n, 3\) points"):
        grid.places(np.zeros((4, 2)), depth=2, relative_to=np.zeros(3), out=good)
