"""Packed voxel keys: their parallel radix order and runs against numpy's stable sort."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from semantic3d.core.threads import thread_limit
from semantic3d.spatial.voxels import MAX_CELL, compute_cells, key_order, key_runs, pack_keys


@settings(max_examples=60, deadline=None)
@given(
    cells=arrays(
        np.int64,
        st.tuples(st.integers(0, 300), st.just(3)),
        elements=st.one_of(st.integers(-3, 3), st.integers(-MAX_CELL, MAX_CELL)),
    ),
    threads=st.sampled_from([1, 3]),
)
def test_key_order_and_runs_are_numpys_stable_sort(cells: np.ndarray, threads: int) -> None:
    keys = pack_keys(cells)
    with thread_limit(threads):
        order = key_order(keys)
        starts = key_runs(keys, order)
    np.testing.assert_array_equal(order, np.argsort(keys, kind="stable"))
    ordered = keys[order]
    change = np.flatnonzero(ordered[1:] != ordered[:-1]) + 1
    expected = np.concatenate(([0], change, [keys.size])) if keys.size else np.zeros(1)
    np.testing.assert_array_equal(starts, expected)


def test_many_keys_over_several_passes_and_blocks() -> None:
    """A million keys whose parts span 16, 12 and 9 bits (four passes), many repeated."""
    rng = np.random.default_rng(4)
    cells = np.stack(
        [
            rng.integers(-30_000, 35_000, 1 << 20),
            rng.integers(0, 4000, 1 << 20),
            rng.integers(-200, 300, 1 << 20),
        ],
        axis=1,
    )
    cells[3::3] = cells[1:-2:3]  # repeated keys
    keys = pack_keys(cells)
    with thread_limit(2):
        order = key_order(keys)
    np.testing.assert_array_equal(order, np.argsort(keys, kind="stable"))


@settings(max_examples=40, deadline=None)
@given(
    xyz=arrays(
        np.float64, st.tuples(st.integers(0, 50), st.just(3)), elements=st.floats(-1e3, 1e3)
    ),
    size=st.sampled_from([0.025, 0.1, 0.7]),
)
def test_cells_are_numpys_floor(xyz: np.ndarray, size: float) -> None:
    origin = np.array([1.5, -2.25, 0.1])
    expected = np.floor((xyz - origin) / size).astype(np.int64)
    np.testing.assert_array_equal(compute_cells(xyz, origin=origin, voxel_size_m=size), expected)


def test_cells_and_keys_of_a_wrong_shape_are_named() -> None:
    import pytest

    from semantic3d.core.errors import ShapeError

    with pytest.raises(ShapeError, match=r"xyz: expected \(n, 3\) coordinates, found \(4, 2\)"):
        compute_cells(np.zeros((4, 2)), origin=np.zeros(3), voxel_size_m=0.1)
    with pytest.raises(ShapeError, match=r"cells: expected \(n, 3\) cells, found \(3,\)"):
        pack_keys(np.zeros(3, np.int64))
    # a strided view (a slice of wider cells) packs like its copy
    wide = np.arange(24, dtype=np.int64).reshape(4, 6)
    np.testing.assert_array_equal(pack_keys(wide[:, ::2]), pack_keys(wide[:, ::2].copy()))


@settings(max_examples=40, deadline=None)
@given(
    x_span=st.integers(0, 2**31 - 1),
    y_span=st.integers(0, 2**31 - 1),
    n=st.integers(0, 5000),
    seed=st.integers(0, 2**32 - 1),
    threads=st.sampled_from([1, 3]),
)
def test_two_part_codes_sort_as_numbers(
    x_span: int, y_span: int, n: int, seed: int, threads: int
) -> None:
    """Codes ``(ix << 31) | iy`` (the cylinders' cells) sorted with ``bits=31``: numpy's
    stable order, and the runs of equal codes."""
    rng = np.random.default_rng(seed)
    codes = (rng.integers(0, x_span + 1, n) << 31) | rng.integers(0, y_span + 1, n)
    if n > 10:
        codes[n // 2 :] = codes[: n - n // 2]  # repeated codes
    with thread_limit(threads):
        order = key_order(codes, bits=31)
        starts = key_runs(codes, order) if n else np.zeros(1, np.int64)
    np.testing.assert_array_equal(order, np.argsort(codes, kind="stable"))
    ordered = codes[order]
    change = np.flatnonzero(ordered[1:] != ordered[:-1]) + 1
    expected = np.concatenate(([0], change, [n])) if n else np.zeros(1)
    np.testing.assert_array_equal(starts, expected)
