"""Small confusion updates are counted with numpy, long ones by the compiled kernel: same counts."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from semantic3d.metrics import confusion
from semantic3d.metrics._confusion_kernel import accumulate


@settings(max_examples=30, deadline=None)
@given(
    pairs=st.lists(st.tuples(st.integers(0, 8), st.integers(0, 8)), max_size=200),
    n_classes=st.sampled_from([8, 9]),
)
def test_numpy_counts_equal_the_kernel(pairs: list[tuple[int, int]], n_classes: int) -> None:
    y_true = np.array([t for t, _ in pairs], np.uint8)
    y_pred = np.array([p for _, p in pairs], np.uint8)
    small = np.zeros((4, n_classes + 1, n_classes + 1), np.int64)
    confusion._accumulate(y_true, y_pred, small)  # below the threshold: numpy
    compiled = np.zeros_like(small)
    accumulate(y_true, y_pred, compiled)
    np.testing.assert_array_equal(small.sum(axis=0), compiled.sum(axis=0))


def test_long_updates_go_to_the_kernel_with_the_same_matrix() -> None:
    rng = np.random.default_rng(0)
    n = confusion._SMALL_UPDATE + 1
    y_true, y_pred = rng.integers(0, 9, n), rng.integers(0, 9, n)
    matrix = confusion.ConfusionMatrix()
    matrix.update(y_true, y_pred)  # one long update: the kernel
    pieces = confusion.ConfusionMatrix()
    for start in range(0, n, 1000):  # short ones: numpy
        pieces.update(y_true[start : start + 1000], y_pred[start : start + 1000])
    np.testing.assert_array_equal(matrix.compute(), pieces.compute())
    assert matrix.n_points == pieces.n_points == int(np.count_nonzero(y_true))
