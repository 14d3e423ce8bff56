"""``CovarianceModel``: a fitted classifier with everything needed to reuse it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from semantic3d.baselines.covariance.config import CovarianceConfig
from semantic3d.baselines.covariance.estimator import CovarianceClassifier
from semantic3d.core.errors import ShapeError


@dataclass(frozen=True, slots=True)
class CovarianceModel:
    """A trained covariance baseline.

    Attributes:
        classifier: the fitted :class:`CovarianceClassifier`.
        config: the resolved configuration it was trained with.
        feature_names: its input columns, in order.
        training_scans: names of the scans it was trained on.
        n_training_points: sampled training points per label value.
        seed: seed of sampling and forest.
        package_version: semantic3d version that trained it.
        training_time_s: wall time of feature computation plus fitting.
    """

    classifier: CovarianceClassifier
    config: CovarianceConfig
    feature_names: tuple[str, ...]
    training_scans: tuple[str, ...]
    n_training_points: dict[int, int]
    seed: int
    package_version: str
    training_time_s: float

    @property
    def label_values(self) -> tuple[int, ...]:
        """Label values the classifier can predict."""
        return tuple(int(v) for v in self.classifier.classes_)

    def predict_rows(self, values: NDArray[np.float32]) -> NDArray[np.uint8]:
        """Label values of feature rows ``(n, n_features)`` in ``feature_names`` order."""
        if values.ndim != 2 or values.shape[1] != len(self.feature_names):
            raise ShapeError(
                f"feature rows: expected (n, {len(self.feature_names)}), found {values.shape}"
            )
        if values.shape[0] == 0:
            return np.empty(0, np.uint8)
        proba = self.classifier.compiled_.predict_proba(values)
        classes = np.asarray(self.classifier.classes_, dtype=np.uint8)
        labels: NDArray[np.uint8] = classes[np.argmax(proba, axis=1)]
        return labels
