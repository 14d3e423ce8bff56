"""Scores from a confusion matrix: IoU, overall accuracy, precision, recall, F1.

Pure functions of a matrix whose rows are ground truth and columns predictions (class
indices). For class ``i`` with ``tp = c_ii``, ``fn = Σ_j≠i c_ij`` (+ points of class ``i``
predicted as no class) and ``fp = Σ_k≠i c_ki``:

- ``IoU_i = tp / (tp + fn + fp)`` (the semantic3D.net definition);
- ``precision_i = tp / (tp + fp)``, ``recall_i = tp / (tp + fn)``,
  ``F1_i = 2 tp / (2 tp + fp + fn)``;
- ``overall_accuracy = Σ c_ii / Σ c_jk`` (all labelled points, unassigned included).

A class absent from both truth and prediction (``tp + fn + fp == 0``) is *absent*: its
IoU and F1 are NaN and it is left out of ``mean_iou``. A ratio whose denominator is 0 is
NaN (never a silent 0): precision of a class never predicted, recall of a class absent from
the ground truth.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from semantic3d.core.errors import ShapeError


@dataclass(frozen=True, slots=True)
class Scores:
    """Per-class and summary scores of one confusion matrix.

    Attributes:
        iou: ``(n_classes,)`` intersection over union per class, NaN where absent.
        precision: ``(n_classes,)`` NaN where the class was never predicted.
        recall: ``(n_classes,)`` NaN where the class is absent from the ground truth.
        f1: ``(n_classes,)`` NaN where absent.
        mean_iou: mean of ``iou`` over present classes (NaN when none is present).
        overall_accuracy: correctly classified labelled points / labelled points.
        present: ``(n_classes,)`` True where the class occurs in truth or prediction.
        n_points: labelled points counted.
    """

    iou: NDArray[np.float64]
    precision: NDArray[np.float64]
    recall: NDArray[np.float64]
    f1: NDArray[np.float64]
    mean_iou: float
    overall_accuracy: float
    present: NDArray[np.bool_]
    n_points: int

    @property
    def n_classes(self) -> int:
        """Number of classes scored."""
        return int(self.iou.shape[0])

    @property
    def absent_indices(self) -> tuple[int, ...]:
        """Class indices (``value - 1``) absent from both truth and prediction."""
        return tuple(int(i) for i in np.flatnonzero(~self.present))


def _ratio(numerator: NDArray[np.int64], denominator: NDArray[np.int64]) -> NDArray[np.float64]:
    out = np.full(numerator.shape, np.nan, dtype=np.float64)
    np.divide(numerator, denominator, out=out, where=denominator > 0)
    return out


def compute_scores(matrix: ArrayLike, *, unassigned: ArrayLike | None = None) -> Scores:
    """Scores of a square confusion matrix (rows ground truth, columns prediction).

    Args:
        matrix: ``(n, n)`` non-negative integer counts.
        unassigned: optional ``(n,)`` counts of points of each true class that were
            predicted as no class (label value 0); they count as false negatives.

    >>> s = compute_scores([[3, 1], [0, 0]])
    >>> s.iou.tolist(), s.mean_iou, s.overall_accuracy
    ([0.75, 0.0], 0.375, 0.75)
    >>> compute_scores([[2, 0, 0], [0, 0, 0], [0, 0, 2]]).iou.tolist()
    [1.0, nan, 1.0]
    """
    counts = np.asarray(matrix)
    if counts.ndim != 2 or counts.shape[0] != counts.shape[1]:
        raise ShapeError(f"matrix: expected a square (n, n) array, found shape {counts.shape}")
    if counts.dtype.kind not in "ui" or (counts.size and counts.min() < 0):
        raise ShapeError(f"matrix: expected non-negative integer counts, found {counts.dtype}")
    counts = counts.astype(np.int64)
    n = counts.shape[0]
    missed = np.zeros(n, np.int64)
    if unassigned is not None:
        missed = np.asarray(unassigned)
        if missed.shape != (n,) or missed.dtype.kind not in "ui" or (n and missed.min() < 0):
            raise ShapeError(
                f"unassigned: expected ({n},) non-negative integer counts, "
                f"found shape {missed.shape} {missed.dtype}"
            )
        missed = missed.astype(np.int64)

    tp = np.diagonal(counts).copy()
    row = counts.sum(axis=1) + missed
    col = counts.sum(axis=0)
    fn = row - tp
    fp = col - tp
    union = tp + fn + fp
    present = union > 0
    iou = _ratio(tp, union)
    n_points = int(row.sum())
    return Scores(
        iou=iou,
        precision=_ratio(tp, col),
        recall=_ratio(tp, row),
        f1=_ratio(2 * tp, 2 * tp + fp + fn),
        mean_iou=float(iou[present].mean()) if present.any() else float("nan"),
        overall_accuracy=float(tp.sum() / n_points) if n_points else float("nan"),
        present=present,
        n_points=n_points,
    )
