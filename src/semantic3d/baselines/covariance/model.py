"""``CovarianceModel``: a fitted classifier with everything needed to reuse it."""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from semantic3d.baselines.common.prediction import LabelledBlock
from semantic3d.baselines.covariance.config import CovarianceConfig
from semantic3d.baselines.covariance.estimator import CovarianceClassifier
from semantic3d.core.errors import ShapeError
from semantic3d.core.pointcloud import PointCloud


@dataclass(frozen=True, slots=True)
class GridSearchResult:
    """Cross-validated scores of every grid point (``GridSearchCV.cv_results_`` essentials).

    Attributes:
        params: the parameter sets, in grid order.
        mean_scores: mean validation score of each set.
        std_scores: standard deviation across folds.
        fit_time_s: mean fit time of each set.
        best_params: the best set.
        best_score: its mean score.
        scoring: the scikit-learn scorer name.
        n_splits: folds (grouped by scan).
    """

    params: tuple[dict[str, Any], ...]
    mean_scores: NDArray[np.float64]
    std_scores: NDArray[np.float64]
    fit_time_s: NDArray[np.float64]
    best_params: dict[str, Any]
    best_score: float
    scoring: str
    n_splits: int

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (NaN scores as None)."""
        return {
            "scoring": self.scoring,
            "n_splits": self.n_splits,
            "best_params": self.best_params,
            "best_score": _finite(self.best_score),
            "results": [
                {**params, "mean": _finite(mean), "std": _finite(std)}
                for params, mean, std in zip(
                    self.params, self.mean_scores, self.std_scores, strict=True
                )
            ],
        }


def _finite(value: float) -> float | None:
    return float(value) if np.isfinite(value) else None


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
        grid_search: the cross-validation that chose the forest's parameters, when
            training ran one (``config.forest`` then holds the chosen ones).
    """

    classifier: CovarianceClassifier
    config: CovarianceConfig
    feature_names: tuple[str, ...]
    training_scans: tuple[str, ...]
    n_training_points: dict[int, int]
    seed: int
    package_version: str
    training_time_s: float
    grid_search: GridSearchResult | None = None

    @property
    def chunk_size(self) -> int:
        """Points per chunk read while predicting (the configuration's)."""
        return self.config.prediction.chunk_size

    def iter_labelled_blocks(
        self, chunks: Iterable[PointCloud], *, workdir: Path
    ) -> Iterator[LabelledBlock]:
        """Label a streamed scan (the :class:`~semantic3d.baselines.common.Predictor` protocol).

        The scan goes through :func:`~semantic3d.features.scan.iter_scan_features` (whole in
        memory when small, tile by tile otherwise). Each feature row is classified once: in
        voxel mode a row is a level-0 voxel and its label goes to every point inside it
        (they all have the same features, so this *is* per-point prediction); in per-point
        mode every point has its own row.
        """
        from semantic3d.features.scan import iter_scan_features

        prediction = self.config.prediction
        for block in iter_scan_features(
            chunks,
            config=self.config.features,
            max_points_in_memory=prediction.max_points_in_memory,
            tile_size_m=prediction.tile_size_m,
            workdir=workdir / "tiles",
        ):
            row_labels = self.predict_rows(block.table.values)
            yield LabelledBlock(
                block.point_indices,
                row_labels[block.table.point_row],
                block.n_scan_points,
                tiled=block.tiled,
            )

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
