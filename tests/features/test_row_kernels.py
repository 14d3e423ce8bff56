"""The compiled row kernels write what the numpy expressions they replace would, on any
number of threads."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from semantic3d.core.threads import thread_limit
from semantic3d.features._row_kernels import (
    _column_table,
    copy_rows,
    distinct_values,
    exact_rows,
    leading_columns,
    put_rows,
    put_values,
    rows_in_box,
    rows_of_keys,
    store_keys,
    take_rows,
)

THREADS = (1, 3)


@settings(max_examples=60, deadline=None)
@given(
    n_keys=st.integers(0, 60),
    n_rows=st.integers(0, 40),
    seed=st.integers(0, 2**32 - 1),
)
def test_rows_of_keys_equals_searchsorted(n_keys: int, n_rows: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    row_keys = np.unique(rng.integers(-50, 50, n_rows))
    keys = rng.integers(-60, 60, (n_keys, 3))
    if row_keys.size:
        position = np.minimum(np.searchsorted(row_keys, keys), row_keys.size - 1)
        expected = np.where(row_keys[position] == keys, position, -1)
    else:
        expected = np.full(keys.shape, -1)
    for n in THREADS:
        with thread_limit(n):
            np.testing.assert_array_equal(rows_of_keys(keys, row_keys), expected)
            written = keys.copy()  # in place: the same rows, over the keys
            assert rows_of_keys(written, row_keys, in_place=True) is written
            np.testing.assert_array_equal(written, expected)


def _packed(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
    return (x.astype(np.int64) << 42) | (y.astype(np.int64) << 21) | z.astype(np.int64)


@settings(max_examples=60, deadline=None)
@given(
    n_rows=st.integers(1, 400),
    width=st.integers(1, 30),
    height=st.integers(1, 300),
    n_keys=st.integers(0, 300),
    sparse=st.booleans(),
    seed=st.integers(0, 2**32 - 1),
)
def test_rows_of_packed_voxel_keys_through_their_columns_equal_searchsorted(
    n_rows: int, width: int, height: int, n_keys: int, sparse: bool, seed: int
) -> None:
    """A tile's level-0 voxels fill the rectangle of their columns: their keys are found
    through a table of the columns (walls: columns of many voxels); keys of other columns,
    outside the rectangle, missing (-1) or absent from a present column are not found.
    Rows spread over a large rectangle are searched instead."""
    rng = np.random.default_rng(seed)
    spread = 5000 if sparse else width
    x = rng.integers(1000, 1000 + spread, n_rows)
    y = rng.integers(2000, 2000 + width, n_rows)
    z = rng.integers(0, height, n_rows)
    row_keys = np.unique(_packed(x, y, z))
    present = row_keys[rng.integers(0, row_keys.size, n_keys)]
    near = _packed(
        rng.integers(995, 1005 + spread, n_keys),
        rng.integers(1995, 2005 + width, n_keys),
        rng.integers(0, height + 2, n_keys),
    )
    keys = np.where(rng.random(n_keys) < 0.5, present, near)
    keys[rng.random(n_keys) < 0.1] = -1
    keys = keys.reshape(-1, 1)
    position = np.minimum(np.searchsorted(row_keys, keys), row_keys.size - 1)
    expected = np.where(row_keys[position] == keys, position, -1)
    if not sparse:  # a filled rectangle of columns: the table's path
        assert _column_table(row_keys)[3] > 0
    for n in THREADS:
        with thread_limit(n):
            np.testing.assert_array_equal(rows_of_keys(keys, row_keys), expected)


def test_a_tiles_voxels_take_the_column_table_and_sparse_or_negative_keys_do_not() -> None:
    x, y = np.meshgrid(np.arange(64), np.arange(64), indexing="ij")
    tile = np.unique(_packed(x.reshape(-1), y.reshape(-1), np.zeros(x.size, np.int64)))
    assert _column_table(tile)[3] == 64
    apart = np.array([_packed(np.array([0]), np.array([0]), np.array([0]))[0], 1 << 60])
    assert _column_table(apart)[3] == 0
    assert _column_table(np.array([-5, 3], np.int64))[3] == 0
    np.testing.assert_array_equal(rows_of_keys(np.array([3, -5, 4]), np.array([-5, 3])), [1, 0, -1])


def test_rows_of_keys_in_place_takes_only_an_array_it_can_write_over() -> None:
    row_keys = np.arange(5, dtype=np.int64)
    for keys in (
        np.arange(6, dtype=np.int32),
        np.arange(12, dtype=np.int64).reshape(3, 4)[:, :2],
        np.arange(6, dtype=np.int64)[::2],
    ):
        with pytest.raises(ValueError, match="writeable C-contiguous int64"):
            rows_of_keys(keys, row_keys, in_place=True)
    frozen = np.arange(6, dtype=np.int64)
    frozen.flags.writeable = False
    with pytest.raises(ValueError, match="writeable C-contiguous int64"):
        rows_of_keys(frozen, row_keys, in_place=True)


@settings(max_examples=60, deadline=None)
@given(
    m=st.integers(0, 50),
    infinite=st.lists(st.booleans(), min_size=4, max_size=4),
    enough=st.booleans(),
    seed=st.integers(0, 2**32 - 1),
)
def test_exact_rows_equals_the_distance_to_the_nearest_closed_edge(
    m: int, infinite: list[bool], enough: bool, seed: int
) -> None:
    rng = np.random.default_rng(seed)
    queries = rng.uniform(-5.0, 15.0, (m, 3))
    reach = rng.uniform(0.0, 6.0, m)
    # some reaches exactly at the edge: the comparison is strict
    if m:
        reach[::3] = np.abs(queries[::3, 0] - 0.0) - 1e-3
    box = np.array([0.0, 10.0, -1.0, 9.0])
    flags = np.array(infinite)
    gaps = np.column_stack(
        [
            queries[:, 0] - box[0],
            box[1] - queries[:, 0],
            queries[:, 1] - box[2],
            box[3] - queries[:, 1],
        ]
    )
    gaps[:, flags] = np.inf
    expected = enough & (reach * (1.0 + 1e-6) + 1e-3 < gaps.min(axis=1, initial=np.inf))
    for n in THREADS:
        with thread_limit(n):
            found = exact_rows(queries, reach, box, flags, enough, 1e-3)
            np.testing.assert_array_equal(found, expected)


def test_store_keys_writes_exact_rows_only_and_pads_short_lists() -> None:
    rng = np.random.default_rng(4)
    keys = np.arange(100, 120, dtype=np.int64)
    found = rng.integers(0, 20, (30, 3))
    exact = rng.random(30) < 0.6
    for n in THREADS:
        out = np.full((30, 5), 7, np.int64)
        with thread_limit(n):
            store_keys(keys, found, exact, out)
        expected = np.full((30, 5), 7, np.int64)
        expected[exact, :3] = keys[found[exact]]
        expected[exact, 3:] = -1
        np.testing.assert_array_equal(out, expected)


@pytest.mark.parametrize("n", THREADS)
def test_copies_and_gathers_equal_numpy(n: int) -> None:
    rng = np.random.default_rng(n)
    source = rng.random((257, 3))
    rows = rng.integers(0, 257, 400)
    block = rng.random((100, 4)).astype(np.float32)
    inverse = rng.integers(0, 100, 300)
    found = rng.integers(0, 2**31, (50, 11)).astype(np.uint32)
    table = np.zeros((300, 12), np.float32)
    wide = np.zeros((100, 12), np.int64)
    with thread_limit(n):
        np.testing.assert_array_equal(take_rows(source, rows), source[rows])
        np.testing.assert_array_equal(take_rows(source, rows[:0]), source[:0])
        leading = leading_columns(found, 10)
        assert leading.flags.c_contiguous
        np.testing.assert_array_equal(leading, found[:, :10])
        put_rows(block, inverse, table[:, 4:8], 0)  # a column slice
        copy_rows(block, table[:100, 8:12])
        copy_rows(found[:, :10], wide[:50, 2:12])  # uint32 into int64
    np.testing.assert_array_equal(table[:, 4:8], block[inverse])
    np.testing.assert_array_equal(table[:100, 8:12], block)
    assert not table[:, :4].any() and not table[100:, 8:].any()
    np.testing.assert_array_equal(wide[:50, 2:12], found[:, :10])


@pytest.mark.parametrize("n", THREADS)
def test_box_selection_and_puts_equal_numpy(n: int) -> None:
    rng = np.random.default_rng(n)
    xyz = rng.uniform(0.0, 10.0, (500, 3))
    xyz[:5, 0] = 2.0  # on the closed edge
    box = np.array([2.0, 7.0, 1.0, 6.0])
    inside = (xyz[:, 0] >= 2.0) & (xyz[:, 0] <= 7.0) & (xyz[:, 1] >= 1.0) & (xyz[:, 1] <= 6.0)
    keys = rng.integers(0, 10**12, 500)
    with thread_limit(n):
        rows = rows_in_box(xyz, box)
        np.testing.assert_array_equal(rows, np.flatnonzero(inside))
        out = np.zeros((rows.size + 3, 3))
        out_keys = np.zeros(rows.size + 3, np.int64)
        put_rows(xyz, rows, out, 3)
        put_values(keys, rows, out_keys, 3)
    np.testing.assert_array_equal(out[3:], xyz[inside])
    np.testing.assert_array_equal(out_keys[3:], keys[inside])
    assert not out[:3].any() and not out_keys[:3].any()


@settings(max_examples=60, deadline=None)
@given(
    n=st.integers(1, 90_000),
    largest=st.integers(0, 300_000),
    in_order=st.booleans(),
    seed=st.integers(0, 2**32 - 1),
    threads=st.sampled_from(THREADS),
)
def test_distinct_values_equal_numpy_unique(
    n: int, largest: int, in_order: bool, seed: int, threads: int
) -> None:
    """Distinct values, each value's rank, and whether the values already are their own
    distinct values in order (a level's voxels filled in place) on any number of threads."""
    rng = np.random.default_rng(seed)
    values = (
        np.arange(n, dtype=np.int64) * (1 + largest // max(1, n))
        if in_order
        else rng.integers(0, largest + 1, n)
    )
    with thread_limit(threads):
        distinct, inverse, same = distinct_values(values)
    expected, expected_inverse = np.unique(values, return_inverse=True)
    np.testing.assert_array_equal(distinct, expected)
    np.testing.assert_array_equal(inverse, expected_inverse.reshape(-1))
    assert same == (expected.size == n and np.array_equal(expected, values))
