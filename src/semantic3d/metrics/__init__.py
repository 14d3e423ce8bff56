"""Generic maths on label arrays: the ``ConfusionMatrix`` accumulator and scores from a matrix.

Nothing here reads files; see :mod:`semantic3d.evaluation` for the benchmark protocol.
"""

from semantic3d.metrics.confusion import ConfusionMatrix
from semantic3d.metrics.scores import Scores, compute_scores

__all__ = ["ConfusionMatrix", "Scores", "compute_scores"]
