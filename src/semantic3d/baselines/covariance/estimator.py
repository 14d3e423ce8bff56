"""``CovarianceClassifier``: the baseline's random forest as a scikit-learn estimator.

A thin estimator over ``sklearn.ensemble.RandomForestClassifier`` (the classifier of
Hackel et al. 2016) whose prediction runs through the compiled forest of
:mod:`~semantic3d.baselines.covariance.forest`. It takes any feature matrix, so
``GridSearchCV``, pipelines and ``check_estimator`` work as for any classifier; the
semantic3d pipeline feeds it the named multi-scale features.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from semantic3d.baselines.covariance.forest import (
    CompiledClassifier,
    CompiledForest,
    compile_forest,
)
from semantic3d.core.errors import require
from semantic3d.core.threads import thread_budget

_sklearn_base: Any = require("sklearn.base", "ml")
_ensemble: Any = require("sklearn.ensemble", "ml")
_validation: Any = require("sklearn.utils.validation", "ml")
_multiclass: Any = require("sklearn.utils.multiclass", "ml")


class CovarianceClassifier(_sklearn_base.ClassifierMixin, _sklearn_base.BaseEstimator):
    """Random forest on multi-scale covariance features, with compiled prediction.

    Parameters mirror ``RandomForestClassifier``.

    Args:
        n_estimators: number of trees.
        max_depth: maximum tree depth (None: grow until leaves are pure).
        min_samples_leaf: minimum samples in a leaf.
        max_features: features tried per split (``"sqrt"``, a fraction, a count, or None: all).
        class_weight: passed to the forest (training data are already class-balanced
            by :func:`~semantic3d.baselines.covariance.training.sample_training_points`).
        n_jobs: threads for fitting (None: 1, -1: the thread budget, all cores by
            default; see :mod:`semantic3d.core.threads`).
        random_state: seed of the forest.

    Attributes:
        classes_: ``(n_classes,)`` class labels seen in ``fit``.
        n_features_in_: number of feature columns.
        feature_names_in_: column names when ``X`` was a DataFrame.
        forest_: the fitted ``RandomForestClassifier``.
        compiled_: the flattened trees used by ``predict_proba``.
    """

    def __init__(
        self,
        n_estimators: int = 100,
        *,
        max_depth: int | None = None,
        min_samples_leaf: int = 1,
        max_features: str | float | int | None = "sqrt",
        class_weight: str | dict[Any, float] | None = None,
        n_jobs: int | None = None,
        random_state: int | None = None,
    ) -> None:
        self.n_estimators = n_estimators
        self.max_depth = max_depth
        self.min_samples_leaf = min_samples_leaf
        self.max_features = max_features
        self.class_weight = class_weight
        self.n_jobs = n_jobs
        self.random_state = random_state

    def fit(self, X: ArrayLike, y: ArrayLike) -> CovarianceClassifier:
        """Fit the forest on feature rows ``X`` and labels ``y``; returns ``self``."""
        X_checked, y_checked = _validation.validate_data(self, X, y, dtype=np.float32)
        _multiclass.check_classification_targets(y_checked)
        forest = _ensemble.RandomForestClassifier(
            n_estimators=self.n_estimators,
            max_depth=self.max_depth,
            min_samples_leaf=self.min_samples_leaf,
            max_features=self.max_features,
            class_weight=self.class_weight,
            n_jobs=_n_jobs(self.n_jobs),
            random_state=self.random_state,
        )
        forest.fit(X_checked, y_checked)
        self.forest_ = forest
        self.classes_ = forest.classes_
        self.compiled_: CompiledForest = compile_forest(
            forest.estimators_, n_features=X_checked.shape[1]
        )
        return self

    def predict_proba(self, X: ArrayLike) -> NDArray[np.float64]:
        """``(n_rows, n_classes)`` class probabilities (columns follow ``classes_``)."""
        _validation.check_is_fitted(self)
        X_checked = _validation.validate_data(self, X, dtype=np.float32, reset=False)
        return self.compiled_.predict_proba(X_checked)

    def predict(self, X: ArrayLike) -> NDArray[Any]:
        """The most probable class of every row."""
        proba = self.predict_proba(X)
        result: NDArray[Any] = self.classes_[np.argmax(proba, axis=1)]
        return result

    def compact(self) -> CompiledClassifier:
        """What prediction needs of the fitted estimator, without scikit-learn objects
        (what model files hold)."""
        _validation.check_is_fitted(self)
        return CompiledClassifier(
            classes_=np.asarray(self.classes_),
            compiled_=self.compiled_,
            feature_importances_=np.asarray(self.forest_.feature_importances_, np.float64),
            params=self.get_params(),
        )

    def __sklearn_tags__(self) -> Any:
        tags = super().__sklearn_tags__()
        tags.input_tags.allow_nan = False
        return tags


def _n_jobs(n_jobs: int | None) -> int | None:
    """scikit-learn's ``n_jobs`` with "all cores" (``-1``; ``-2`` all but one, ...) read
    as the package's thread budget (:mod:`semantic3d.core.threads`), so ``--threads``
    caps the forest too. The fitted forest does not depend on it."""
    if n_jobs is None or n_jobs > 0:
        return n_jobs
    return max(1, thread_budget() + 1 + n_jobs)
