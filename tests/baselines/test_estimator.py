"""CovarianceClassifier: scikit-learn's estimator checks and the compiled forest."""

from __future__ import annotations

import numpy as np
import pytest
from sklearn.ensemble import RandomForestClassifier
from sklearn.utils.estimator_checks import parametrize_with_checks

from semantic3d.baselines.covariance.estimator import CovarianceClassifier
from semantic3d.baselines.covariance.forest import _float32_floor, compile_forest
from semantic3d.core.errors import ShapeError
from semantic3d.core.threads import thread_limit


@parametrize_with_checks([CovarianceClassifier(n_estimators=5, random_state=0)])
def test_scikit_learn_estimator_checks(estimator, check) -> None:  # type: ignore[no-untyped-def]
    check(estimator)


def test_compiled_forest_reproduces_scikit_learn_predictions() -> None:
    rng = np.random.default_rng(0)
    x = rng.normal(size=(3000, 12)).astype(np.float32)
    y = (x[:, 0] > 0).astype(int) + 2 * (x[:, 1] * x[:, 2] > 0.3) + 4 * (x[:, 3] > 1)
    clf = CovarianceClassifier(n_estimators=15, max_depth=12, random_state=0).fit(x, y)
    test = rng.normal(size=(5000, 12)).astype(np.float32)
    expected = clf.forest_.predict_proba(test)
    np.testing.assert_allclose(clf.predict_proba(test), expected, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(clf.predict(test), clf.forest_.predict(test))
    assert list(clf.classes_) == sorted(set(y))
    # blocks of rows taken as threads come free: the same bytes on any number of threads
    with thread_limit(1):
        one = clf.predict_proba(test)
    with thread_limit(3):
        np.testing.assert_array_equal(clf.predict_proba(test), one)


def test_features_exactly_on_a_threshold_go_the_same_way() -> None:
    x = np.array([[0.1], [0.2], [0.3], [0.4]], np.float32)
    forest = RandomForestClassifier(n_estimators=1, bootstrap=False, random_state=0)
    forest.fit(x, [0, 0, 1, 1])
    threshold = forest.estimators_[0].tree_.threshold[0]  # midpoint 0.25 in float64
    probes = np.array([[np.float32(threshold)], [np.nextafter(np.float32(threshold), 1)]])
    compiled = compile_forest(forest.estimators_, n_features=1)
    np.testing.assert_array_equal(compiled.predict_proba(probes), forest.predict_proba(probes))


def test_trees_of_every_depth_in_one_forest() -> None:
    # the walk runs each tree for its depth: a lone leaf, stumps and deep trees side by side,
    # with row counts that leave partial groups of walkers and partial blocks
    from sklearn.tree import DecisionTreeClassifier

    rng = np.random.default_rng(2)
    x = rng.normal(size=(600, 5)).astype(np.float32)
    y = (x[:, 0] > 0).astype(int) + (x[:, 1] > 0.5)
    trees = [
        DecisionTreeClassifier(max_depth=depth, min_samples_split=split, random_state=0).fit(x, y)
        for depth, split in [(None, 10**6), (1, 2), (3, 2), (None, 2)]
    ]
    assert [tree.get_depth() for tree in trees][:2] == [0, 1]
    compiled = compile_forest(trees, n_features=5)
    assert compiled.predict_proba(np.empty((0, 5), np.float32)).shape == (0, 3)
    for n_rows in (1, 15, 17, 256, 1000):
        test = rng.normal(size=(n_rows, 5)).astype(np.float32)
        expected = np.mean([tree.predict_proba(test) for tree in trees], axis=0)
        np.testing.assert_allclose(compiled.predict_proba(test), expected, atol=1e-12)


def test_float32_floor_keeps_every_comparison() -> None:
    rng = np.random.default_rng(1)
    thresholds = rng.normal(size=1000)
    floors = _float32_floor(thresholds)
    assert np.all(floors.astype(np.float64) <= thresholds)
    above = np.nextafter(floors, np.float32(np.inf))
    assert np.all(above.astype(np.float64) > thresholds)


def test_wrong_feature_count_is_rejected() -> None:
    clf = CovarianceClassifier(n_estimators=2, random_state=0).fit(np.eye(4), [0, 1, 0, 1])
    with pytest.raises(ValueError, match="4 features"):
        clf.predict(np.zeros((2, 3)))
    with pytest.raises(ShapeError, match=r"features: expected \(n, 4\)"):
        clf.compiled_.predict_proba(np.zeros((2, 3), np.float32))
