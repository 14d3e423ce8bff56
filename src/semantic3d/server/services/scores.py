"""What the database keeps of an evaluation, derived from the :class:`EvaluationResult` alone.

:func:`stored_scores` is the one function that turns a result into a submission row's
fields; :func:`result_of` reads the result back. The full result (``result_json``, per-scan
scores included) is the record; three columns repeat parts of it because queries need
them:

- ``mean_iou`` and ``overall_accuracy``: the leaderboard filters on ``mean_iou IS NOT
  NULL`` and orders by both in SQL (index ``ix_submissions_board``);
- ``iou_json`` (per-class IoU): the leaderboard query lists it for every row, which would
  otherwise mean parsing each row's whole result, private per-scan scores included, on
  every rebuild of a public board.

Everything else (point count, confusion matrix) is read from the result when shown.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass

from semantic3d.evaluation import EvaluationResult
from semantic3d.server.models import Submission


def finite_or_none(value: float) -> float | None:
    """``value`` as a float, or ``None`` for NaN and infinities (JSON and SQL have no NaN).

    >>> finite_or_none(0.5), finite_or_none(float("nan"))
    (0.5, None)
    """
    number = float(value)
    return number if math.isfinite(number) else None


@dataclass(frozen=True, slots=True)
class StoredScores:
    """A submission row's evaluation fields (column name -> value)."""

    mean_iou: float | None
    overall_accuracy: float | None
    iou_json: str
    result_json: str

    def columns(self) -> dict[str, float | str | None]:
        """The fields as ``{column: value}`` for an ``UPDATE``."""
        return asdict(self)


def stored_scores(result: EvaluationResult) -> StoredScores:
    """The row fields of ``result``: NaN scores (absent classes, nothing scored) as ``None``."""
    scores = result.scores
    return StoredScores(
        mean_iou=finite_or_none(scores.mean_iou),
        overall_accuracy=finite_or_none(scores.overall_accuracy),
        iou_json=json.dumps([finite_or_none(value) for value in scores.iou.tolist()]),
        result_json=json.dumps(result.to_dict(), sort_keys=True),
    )


def result_of(submission: Submission) -> EvaluationResult | None:
    """The stored evaluation result (``None`` until evaluated)."""
    if submission.result_json is None:
        return None
    return EvaluationResult.from_dict(json.loads(submission.result_json))


def stored_iou(iou_json: str | None) -> tuple[float | None, ...]:
    """The per-class IoU column as a tuple (class order, ``None`` where absent)."""
    return tuple(json.loads(iou_json or "[]"))
