"""ConfusionMatrix: hand-computed counts, sklearn reference, streaming properties."""

from __future__ import annotations

import doctest

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from sklearn.metrics import confusion_matrix

import semantic3d.metrics.confusion
import semantic3d.metrics.scores
from semantic3d.core.errors import DataFormatError, ShapeError
from semantic3d.metrics import ConfusionMatrix


def test_hand_computed_matrix_rows_are_ground_truth() -> None:
    cm = ConfusionMatrix(n_classes=3)
    # (truth, prediction): 1->1 twice, 1->3 once, 2->1 once, 3->3 once; truth 0 dropped.
    cm.update(np.array([1, 1, 1, 2, 3, 0, 0], np.uint8), np.array([1, 1, 3, 1, 3, 2, 3], np.uint8))
    expected = np.array([[2, 0, 1], [1, 0, 0], [0, 0, 1]])
    np.testing.assert_array_equal(cm.compute(), expected)
    assert cm.compute().dtype == np.int64
    assert cm.n_points == 5


def test_updates_accumulate_and_reset_forgets() -> None:
    cm = ConfusionMatrix()
    cm.update([8, 8], [8, 1])
    cm.update([8], [8])
    assert cm.compute()[7, 7] == 2
    assert cm.compute()[7, 0] == 1
    cm.reset()
    assert cm.compute().sum() == 0
    assert cm.n_points == 0


def test_prediction_zero_is_an_error_charged_to_the_true_class() -> None:
    cm = ConfusionMatrix(n_classes=2)
    cm.update([1, 1, 1, 2], [1, 0, 0, 2])
    np.testing.assert_array_equal(cm.compute(), [[1, 0], [0, 1]])
    np.testing.assert_array_equal(cm.compute_unassigned(), [2, 0])
    scores = cm.compute_scores()
    # class 1: tp 1, fn 2 (both unassigned), fp 0 -> IoU 1/3; class 2 untouched.
    np.testing.assert_allclose(scores.iou, [1 / 3, 1.0])
    np.testing.assert_allclose(scores.recall, [1 / 3, 1.0])
    np.testing.assert_allclose(scores.precision, [1.0, 1.0])
    assert scores.overall_accuracy == pytest.approx(2 / 4)
    assert scores.n_points == 4


def test_matches_sklearn_on_random_data() -> None:
    rng = np.random.default_rng(42)
    y_true = rng.integers(0, 9, 100_000).astype(np.uint8)
    y_pred = rng.integers(1, 9, 100_000).astype(np.uint8)
    cm = ConfusionMatrix()
    for start in range(0, y_true.size, 7_777):  # uneven chunks
        cm.update(y_true[start : start + 7_777], y_pred[start : start + 7_777])
    keep = y_true > 0
    reference = confusion_matrix(y_true[keep], y_pred[keep], labels=np.arange(1, 9))
    np.testing.assert_array_equal(cm.compute(), reference)


def test_accepts_any_integer_dtype() -> None:
    cm = ConfusionMatrix(n_classes=3)
    cm.update(np.array([1, 2, 3], np.int64), np.array([1, 2, 2], np.uint16))
    np.testing.assert_array_equal(cm.compute(), [[1, 0, 0], [0, 1, 0], [0, 1, 0]])


@pytest.mark.parametrize(
    ("y_true", "y_pred", "error", "match"),
    [
        ([1, 9], [1, 1], DataFormatError, r"y_true: expected label values 0\.\.8 .* found 9"),
        ([1, 1], [1, 12], DataFormatError, r"y_pred: expected label values 0\.\.8 .* found 12"),
        ([1, -1], [1, 1], DataFormatError, r"y_true: .* found -1"),
        (
            [1.0, 2.0],
            [1, 2],
            ShapeError,
            r"y_true: expected integer label values, found dtype float64",
        ),
        ([1, 2, 3], [1, 2], ShapeError, r"expected equal lengths, found 3 and 2"),
        ([[1, 2]], [[1, 2]], ShapeError, r"y_true: expected a 1-D array"),
    ],
)
def test_bad_input_is_rejected_and_counts_stay_unchanged(
    y_true: list, y_pred: list, error: type[Exception], match: str
) -> None:
    cm = ConfusionMatrix()
    with pytest.raises(error, match=match):
        cm.update(np.asarray(y_true), np.asarray(y_pred))
    assert cm.n_points == 0


def test_added_counts_equal_the_pairs_they_count() -> None:
    rng = np.random.default_rng(5)
    y_true, y_pred = rng.integers(0, 9, 500), rng.integers(0, 9, 500)
    counts = np.zeros((9, 9), np.int32)
    np.add.at(counts, (y_true, y_pred), 1)
    added, updated = ConfusionMatrix(), ConfusionMatrix()
    added.add_counts(counts)
    updated.update(y_true, y_pred)
    np.testing.assert_array_equal(added.compute(), updated.compute())
    np.testing.assert_array_equal(added.compute_unassigned(), updated.compute_unassigned())
    assert added.n_points == updated.n_points


@pytest.mark.parametrize(
    ("counts", "error", "message"),
    [
        (
            np.zeros((8, 8), np.int64),
            ShapeError,
            r"expected a \(9, 9\) integer array, found shape \(8, 8\)",
        ),
        (np.zeros((9, 9)), ShapeError, "of float64"),
        (-np.eye(9, dtype=np.int64), DataFormatError, "non-negative counts, found -1"),
    ],
)
def test_added_counts_are_checked_and_nothing_is_added_on_error(
    counts: np.ndarray, error: type[Exception], message: str
) -> None:
    matrix = ConfusionMatrix()
    matrix.update([1, 2], [1, 1])
    with pytest.raises(error, match=message):
        matrix.add_counts(counts)
    assert matrix.n_points == 2


def test_merge_checks_class_count() -> None:
    with pytest.raises(ShapeError, match="expected a matrix with 8 classes, found 3"):
        ConfusionMatrix().merge(ConfusionMatrix(n_classes=3))
    with pytest.raises(TypeError, match="expected a ConfusionMatrix"):
        ConfusionMatrix().merge(np.zeros((8, 8)))  # type: ignore[arg-type]


label_arrays = st.integers(0, 200).flatmap(
    lambda n: st.tuples(
        arrays(np.uint8, n, elements=st.integers(0, 8)),
        arrays(np.uint8, n, elements=st.integers(0, 8)),
    )
)


@settings(max_examples=60, deadline=None)
@given(first=label_arrays, second=label_arrays)
def test_merge_equals_one_update_on_the_concatenation(
    first: tuple[np.ndarray, np.ndarray], second: tuple[np.ndarray, np.ndarray]
) -> None:
    left, right, whole = ConfusionMatrix(), ConfusionMatrix(), ConfusionMatrix()
    left.update(*first)
    right.update(*second)
    left.merge(right)
    whole.update(np.concatenate([first[0], second[0]]), np.concatenate([first[1], second[1]]))
    np.testing.assert_array_equal(left.compute(), whole.compute())
    np.testing.assert_array_equal(left.compute_unassigned(), whole.compute_unassigned())


@settings(max_examples=60, deadline=None)
@given(pair=label_arrays, seed=st.integers(0, 2**32 - 1))
def test_point_order_does_not_matter(pair: tuple[np.ndarray, np.ndarray], seed: int) -> None:
    y_true, y_pred = pair
    order = np.random.default_rng(seed).permutation(y_true.size)
    a, b = ConfusionMatrix(), ConfusionMatrix()
    a.update(y_true, y_pred)
    b.update(y_true[order], y_pred[order])
    np.testing.assert_array_equal(a.compute(), b.compute())


@settings(max_examples=60, deadline=None)
@given(pair=label_arrays, ignored=arrays(np.uint8, st.integers(0, 50), elements=st.integers(0, 8)))
def test_ignored_points_have_no_effect(
    pair: tuple[np.ndarray, np.ndarray], ignored: np.ndarray
) -> None:
    y_true, y_pred = pair
    a, b = ConfusionMatrix(), ConfusionMatrix()
    a.update(y_true, y_pred)
    b.update(
        np.concatenate([y_true, np.zeros(ignored.size, np.uint8)]),
        np.concatenate([y_pred, ignored]),
    )
    np.testing.assert_array_equal(a.compute(), b.compute())
    assert a.n_points == b.n_points


@pytest.mark.parametrize("module", [semantic3d.metrics.confusion, semantic3d.metrics.scores])
def test_doctests(module: object) -> None:
    failures, tried = doctest.testmod(module, raise_on_error=False)  # type: ignore[arg-type]
    assert tried > 0
    assert failures == 0
