"""Cross-validation with folds grouped by scan: which scans each fold holds out, and results.

Scan ``i`` of the sorted list goes to fold ``i mod n_folds`` (:func:`scan_folds`); a fold's
scans are held out, a model is trained on the others and labels them. Each baseline's
``crossval`` module trains and labels; the folds, the optional evaluation sample and the
pooled scores are shared, so two baselines cross-validated with the same arguments are
scored on the same scans and points.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from semantic3d.baselines.common.scans import TrainingDataError
from semantic3d.metrics.scores import Scores

__all__ = [
    "CrossValidationResult",
    "FoldResult",
    "evaluation_sample",
    "scan_folds",
]


@dataclass(frozen=True, slots=True)
class FoldResult:
    """One fold: what it trained on, what it labelled, how well.

    Attributes:
        train_scans: names of its training scans.
        test_scans: names of its held-out scans.
        confusion: its ``(8, 8)`` confusion matrix (rows truth, columns prediction).
        n_points: held-out points labelled.
        training_time_s: wall time of its training.
        prediction_time_s: wall time of labelling its held-out points.
    """

    train_scans: tuple[str, ...]
    test_scans: tuple[str, ...]
    confusion: NDArray[np.int64]
    n_points: int
    training_time_s: float
    prediction_time_s: float

    @property
    def scores(self) -> Scores:
        """Scores of this fold."""
        from semantic3d.metrics.scores import compute_scores

        return compute_scores(self.confusion)


@dataclass(frozen=True, slots=True)
class CrossValidationResult:
    """Every fold, and the scores of their pooled confusion matrix."""

    folds: tuple[FoldResult, ...]

    @property
    def scores(self) -> Scores:
        """Scores of the summed confusion matrices."""
        from semantic3d.metrics.scores import compute_scores

        return compute_scores(sum(fold.confusion for fold in self.folds))


def scan_folds(names: Sequence[str], n_folds: int) -> list[tuple[str, ...]]:
    """The held-out scans of each fold: sorted scan ``i`` in fold ``i mod n_folds``.

    >>> scan_folds(["c", "a", "b"], 2)
    [('a', 'c'), ('b',)]
    """
    if n_folds < 2 or n_folds > len(names):
        raise TrainingDataError(
            f"cross-validation grouped by scan: expected 2..{len(names)} folds for "
            f"{len(names)} scans, found {n_folds}"
        )
    ordered = sorted(names)
    return [tuple(ordered[i::n_folds]) for i in range(n_folds)]


def evaluation_sample(
    n_points: int, points_per_scan: int | None, *, seed: int, fold: int, scan: int
) -> NDArray[np.int64] | None:
    """The sorted indices of the held-out points a fold labels (None: every point).

    Drawn from ``(seed, fold, scan)``, so another method can be scored on the same points.
    """
    if points_per_scan is None or points_per_scan >= n_points:
        return None
    rng = np.random.default_rng((seed, fold, scan))
    return np.sort(rng.choice(n_points, points_per_scan, replace=False))
