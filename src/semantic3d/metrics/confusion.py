"""``ConfusionMatrix``: a streaming accumulator of (ground truth, prediction) label pairs.

The convention (written once, in ``docs/evaluation.md``):

- arguments are ``(y_true, y_pred)`` and hold label *values* (0 unlabelled, 1..n classes);
- rows of :meth:`ConfusionMatrix.compute` are ground truth, columns predictions, both
  indexed by class *index* ``value - 1``;
- points whose ground truth is 0 are dropped;
- a labelled point predicted 0 ("no class") is an error: it is kept apart from the
  ``(n, n)`` matrix in :meth:`ConfusionMatrix.compute_unassigned` (one count per true
  class), lowers that class's recall and IoU and the overall accuracy, and is a false
  positive of no class. Benchmark submissions must use 1..n, so it is always zero there.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from semantic3d.core.classes import N_CLASSES
from semantic3d.core.errors import DataFormatError, ShapeError
from semantic3d.metrics.scores import Scores, compute_scores

_LANES = 4  # counter lanes of the compiled kernel (metrics._confusion_kernel.LANES)
_SMALL_UPDATE = 1 << 16
"""Updates up to this many pairs are counted with numpy (same counts as the kernel)."""


def _accumulate(
    y_true: NDArray[np.uint8], y_pred: NDArray[np.uint8], counts: NDArray[np.int64]
) -> None:
    """Add the pairs to ``counts`` (lanes, true value, predicted value)."""
    if y_true.shape[0] <= _SMALL_UPDATE:
        # Loading numba costs ~1 CPU-second, more than counting a small update with numpy.
        size = counts.shape[1]
        pairs = y_true.astype(np.intp) * size + y_pred
        counts[0] += np.bincount(pairs, minlength=size * size).reshape(size, size)
        return
    from semantic3d.metrics._confusion_kernel import accumulate

    accumulate(y_true, y_pred, counts)


def _as_label_values(values: ArrayLike, *, name: str, n_classes: int) -> NDArray[np.uint8]:
    """``values`` as a contiguous 1-D uint8 array of label values 0..n_classes."""
    arr = np.asarray(values)
    if arr.ndim != 1:
        raise ShapeError(f"{name}: expected a 1-D array of label values, found shape {arr.shape}")
    if arr.dtype.kind not in "ui":
        raise ShapeError(f"{name}: expected integer label values, found dtype {arr.dtype}")
    if arr.size:
        low, high = int(arr.min()), int(arr.max())
        if low < 0 or high > n_classes:
            bad = low if low < 0 else high
            raise DataFormatError(
                f"{name}: expected label values 0..{n_classes} "
                f"(0 unlabelled, 1..{n_classes} classes), found {bad}"
            )
    return np.ascontiguousarray(arr, dtype=np.uint8)


class ConfusionMatrix:
    """Accumulates a confusion matrix over chunks of label values.

    ``update`` may be called any number of times (one chunk of a scan at a time); the
    result does not depend on how the points are split into chunks, nor on their order.
    Counts are int64, so billions of points do not overflow.

    >>> cm = ConfusionMatrix(n_classes=3)
    >>> cm.update([1, 1, 2, 3, 0], [1, 2, 2, 3, 3])
    >>> cm.compute()
    array([[1, 1, 0],
           [0, 1, 0],
           [0, 0, 1]])
    """

    def __init__(self, n_classes: int = N_CLASSES) -> None:
        if not 1 <= n_classes <= 254:
            raise ValueError(f"n_classes: expected 1..254, found {n_classes}")
        self.n_classes = n_classes
        # Indexed by label VALUE (0..n): row 0 holds unlabelled ground truth (dropped),
        # column 0 labelled points predicted 0 (unassigned).
        self._counts = np.zeros((_LANES, n_classes + 1, n_classes + 1), dtype=np.int64)

    def update(self, y_true: ArrayLike, y_pred: ArrayLike) -> None:
        """Add pairs of ground-truth and predicted label values (0..n_classes).

        Raises:
            ShapeError: the arrays are not 1-D integer arrays of equal length.
            DataFormatError: a value is outside 0..n_classes.
        """
        t = _as_label_values(y_true, name="y_true", n_classes=self.n_classes)
        p = _as_label_values(y_pred, name="y_pred", n_classes=self.n_classes)
        if t.shape != p.shape:
            raise ShapeError(
                f"y_true and y_pred: expected equal lengths, found {t.shape[0]} and {p.shape[0]}"
            )
        _accumulate(t, p, self._counts)

    def add_counts(self, counts: ArrayLike) -> None:
        """Add pairs already counted: ``counts[t, p]`` pairs of truth value t, prediction p.

        ``counts`` is ``(n_classes + 1, n_classes + 1)``, indexed by label value like
        :meth:`update`'s pairs (row and column 0 included), non-negative integers.

        Raises:
            ShapeError: ``counts`` has another shape or is not integer.
            DataFormatError: a count is negative.
        """
        arr = np.asarray(counts)
        size = self.n_classes + 1
        if arr.shape != (size, size) or arr.dtype.kind not in "ui":
            raise ShapeError(
                f"counts: expected a ({size}, {size}) integer array, "
                f"found shape {arr.shape} of {arr.dtype}"
            )
        if arr.size and int(arr.min()) < 0:
            raise DataFormatError(f"counts: expected non-negative counts, found {int(arr.min())}")
        self._counts[0] += arr.astype(np.int64, copy=False)

    def _totals(self) -> NDArray[np.int64]:
        totals: NDArray[np.int64] = self._counts.sum(axis=0)
        return totals

    def compute(self) -> NDArray[np.int64]:
        """The ``(n_classes, n_classes)`` int64 matrix: rows ground truth, columns prediction."""
        return np.ascontiguousarray(self._totals()[1:, 1:])

    def compute_unassigned(self) -> NDArray[np.int64]:
        """Per true class, the labelled points predicted 0 (counted as errors)."""
        return np.ascontiguousarray(self._totals()[1:, 0])

    def compute_scores(self) -> Scores:
        """IoU, accuracy, precision, recall and F1 of everything accumulated so far.

        Prefer this to ``compute_scores(cm.compute())``: it also charges predictions of 0
        (see :meth:`compute_unassigned`) to their true class.
        """
        return compute_scores(self.compute(), unassigned=self.compute_unassigned())

    @property
    def n_points(self) -> int:
        """Labelled points accumulated (ground truth 1..n_classes), unassigned included."""
        return int(self._totals()[1:].sum())

    def merge(self, other: ConfusionMatrix) -> None:
        """Add the counts of ``other`` (e.g. from another worker or scan) to this one."""
        if not isinstance(other, ConfusionMatrix):
            raise TypeError(f"merge: expected a ConfusionMatrix, found {type(other).__name__}")
        if other.n_classes != self.n_classes:
            raise ShapeError(
                f"merge: expected a matrix with {self.n_classes} classes, found {other.n_classes}"
            )
        self._counts[0] += other._totals()

    def reset(self) -> None:
        """Forget every count."""
        self._counts[...] = 0

    def __repr__(self) -> str:
        return f"ConfusionMatrix(n_classes={self.n_classes}, n_points={self.n_points})"
