"""Generic maths on label arrays: the ``ConfusionMatrix`` accumulator and scores from a matrix.

Nothing here reads files; see :mod:`semantic3d.evaluation` for the benchmark protocol.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from semantic3d.core.lazy import lazy_exports

if TYPE_CHECKING:
    from semantic3d.metrics.confusion import ConfusionMatrix
    from semantic3d.metrics.scores import Scores, compute_scores

__all__ = ["ConfusionMatrix", "Scores", "compute_scores"]

__getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "ConfusionMatrix": "semantic3d.metrics.confusion",
        "Scores": "semantic3d.metrics.scores",
        "compute_scores": "semantic3d.metrics.scores",
    },
)
