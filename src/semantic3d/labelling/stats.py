"""Per-class counts and the confusion of a prediction against the labels, for a selection.

The viewer as an error-analysis tool: for the points of the working set (``scope
"working"``) or the points in the current view (``scope "view"``: inside the camera's
frustum, in a shown layer), count the points of each label value and, when the session
shows a prediction, the confusion matrix of prediction against labels, with the
benchmark's convention (rows ground truth, columns prediction, points whose ground truth
is 0 left out; :mod:`semantic3d.metrics`) and its per-class scores.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from semantic3d.core.classes import N_CLASSES
from semantic3d.labelling import _op_kernels as kernels
from semantic3d.labelling import geometry
from semantic3d.labelling.errors import OperationError
from semantic3d.labelling.session import BLOCK_POINTS, LabelSession, _Running
from semantic3d.metrics.scores import compute_scores

__all__ = ["selection_stats"]


def _finite_list(values: Any) -> list[float | None]:
    return [None if not np.isfinite(v) else round(float(v), 6) for v in values]


def selection_stats(
    session: LabelSession, *, scope: str, view_projection: ArrayLike | None = None
) -> dict[str, Any]:
    """Counts and confusion of the points of ``scope`` (``"working"`` or ``"view"``)."""
    if scope not in ("working", "view"):
        raise OperationError(f"scope: expected 'working' or 'view', found {scope!r}")
    matrix = np.zeros((N_CLASSES + 1, N_CLASSES + 2), np.int64)
    prediction = session.prediction
    with session.lock, _Running(session, f"counts of the {scope}"):
        if scope == "working":
            for start in range(0, session.n_points, BLOCK_POINTS):
                stop = min(start + BLOCK_POINTS, session.n_points)
                session.progress.update(start)
                if prediction is not None:
                    kernels.confusion(
                        session.labels, prediction, session.working, start, stop, matrix
                    )
                else:
                    kernels.masked_layer_counts(
                        session.labels[start:stop],
                        session.working[start:stop],
                        matrix[:, N_CLASSES + 1],
                    )
        else:
            if view_projection is None:
                raise OperationError(
                    "view_projection: expected the camera's 16 numbers, found none"
                )
            camera = geometry._as_matrix(view_projection)
            shown = ~session.hidden

            def count(start: int, xyz: NDArray[np.float64]) -> NDArray[np.int64]:
                block_prediction = (
                    prediction[start : start + len(xyz)]
                    if prediction is not None
                    else np.full(len(xyz), 255, np.uint8)
                )
                block_matrix = np.zeros_like(matrix)
                kernels.view_confusion(
                    xyz, 0, session.origin, session.labels[start : start + len(xyz)],
                    block_prediction, camera, shown, block_matrix,
                )  # fmt: skip
                return block_matrix

            for block_matrix in session.map_blocks(count, active_only=False):
                assert block_matrix is not None
                matrix += block_matrix
    counts = matrix.sum(axis=1)
    result: dict[str, Any] = {
        "scope": scope,
        "n_points": int(counts.sum()),
        "counts": counts.tolist(),
        "has_prediction": prediction is not None,
    }
    if prediction is not None:
        predicted_counts = matrix[:, : N_CLASSES + 1].sum(axis=0)
        confusion = matrix[1:, 1 : N_CLASSES + 1]
        unassigned = matrix[1:, 0] + matrix[1:, N_CLASSES + 1]
        scores = compute_scores(confusion, unassigned=unassigned)
        result.update(
            {
                "prediction_counts": predicted_counts.tolist(),
                "confusion": confusion.tolist(),
                "unassigned": unassigned.tolist(),
                "unlabelled_truth": int(counts[0]),
                "precision": _finite_list(scores.precision),
                "recall": _finite_list(scores.recall),
                "iou": _finite_list(scores.iou),
                "overall_accuracy": None
                if not np.isfinite(scores.overall_accuracy)
                else float(scores.overall_accuracy),
            }
        )
    return result
