"""compute_scores: the IoU definition, absent classes, the sklearn reference."""

from __future__ import annotations

import math

import numpy as np
import pytest
from sklearn.metrics import accuracy_score, jaccard_score, precision_recall_fscore_support

from semantic3d.core.errors import ShapeError
from semantic3d.metrics import ConfusionMatrix, compute_scores


def test_iou_is_tp_over_tp_plus_row_and_column_errors() -> None:
    matrix = np.array([[5, 1, 2], [3, 4, 0], [0, 1, 6]])
    scores = compute_scores(matrix)
    # class 0: tp 5, row errors 1 + 2, column errors 3 + 0 -> 5 / 11
    # class 1: tp 4, row errors 3, column errors 1 + 1 -> 4 / 9
    # class 2: tp 6, row errors 1, column errors 2 -> 6 / 9
    np.testing.assert_allclose(scores.iou, [5 / 11, 4 / 9, 6 / 9])
    np.testing.assert_allclose(scores.precision, [5 / 8, 4 / 6, 6 / 8])
    np.testing.assert_allclose(scores.recall, [5 / 8, 4 / 7, 6 / 7])
    np.testing.assert_allclose(scores.f1, [10 / 16, 8 / 13, 12 / 15])
    assert scores.mean_iou == pytest.approx((5 / 11 + 4 / 9 + 6 / 9) / 3)
    assert scores.overall_accuracy == pytest.approx(15 / 22)
    assert scores.n_points == 22
    assert scores.present.all()


def test_absent_class_is_nan_left_out_of_the_mean_and_reported() -> None:
    matrix = np.zeros((4, 4), np.int64)
    matrix[0, 0], matrix[0, 1], matrix[2, 2] = 3, 1, 4
    scores = compute_scores(matrix)
    assert math.isnan(scores.iou[3]) and math.isnan(scores.f1[3])
    assert scores.absent_indices == (3,)
    # class 1 is only predicted: present, IoU 0, recall undefined
    assert scores.iou[1] == 0.0 and scores.present[1]
    assert math.isnan(scores.recall[1])
    assert math.isnan(scores.precision[3])
    assert scores.mean_iou == pytest.approx((3 / 4 + 0.0 + 1.0) / 3)


def test_empty_matrix_has_undefined_summaries() -> None:
    scores = compute_scores(np.zeros((8, 8), np.int64))
    assert math.isnan(scores.mean_iou) and math.isnan(scores.overall_accuracy)
    assert scores.n_points == 0
    assert scores.absent_indices == tuple(range(8))


def test_matches_sklearn_scores_on_random_data() -> None:
    rng = np.random.default_rng(7)
    y_true = rng.integers(1, 9, 50_000)
    y_pred = np.where(rng.random(50_000) < 0.6, y_true, rng.integers(1, 9, 50_000))
    cm = ConfusionMatrix()
    cm.update(y_true, y_pred)
    scores = cm.compute_scores()
    labels = np.arange(1, 9)
    np.testing.assert_allclose(
        scores.iou, jaccard_score(y_true, y_pred, labels=labels, average=None)
    )
    precision, recall, f1, _ = precision_recall_fscore_support(
        y_true, y_pred, labels=labels, zero_division=np.nan
    )
    np.testing.assert_allclose(scores.precision, precision)
    np.testing.assert_allclose(scores.recall, recall)
    np.testing.assert_allclose(scores.f1, f1)
    assert scores.overall_accuracy == pytest.approx(accuracy_score(y_true, y_pred))


@pytest.mark.parametrize(
    ("matrix", "match"),
    [
        (np.zeros((2, 3), np.int64), r"expected a square \(n, n\) array, found shape \(2, 3\)"),
        (np.zeros(4, np.int64), r"found shape \(4,\)"),
        (np.full((2, 2), -1), "expected non-negative integer counts"),
        (np.zeros((2, 2)), "expected non-negative integer counts, found float64"),
    ],
)
def test_bad_matrix_is_rejected(matrix: np.ndarray, match: str) -> None:
    with pytest.raises(ShapeError, match=match):
        compute_scores(matrix)


def test_bad_unassigned_is_rejected() -> None:
    with pytest.raises(ShapeError, match=r"unassigned: expected \(2,\) non-negative"):
        compute_scores(np.eye(2, dtype=np.int64), unassigned=[1, 2, 3])
