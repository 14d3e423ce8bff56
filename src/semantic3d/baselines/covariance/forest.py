"""Compiled inference for a fitted scikit-learn random forest.

``RandomForestClassifier.predict_proba`` walks one tree at a time over all rows, allocating
an ``(n_rows, n_classes)`` array per tree. Here every tree is flattened into one set of
node arrays and a numba kernel walks blocks of rows through all trees (2-4x faster on
2 cores, measured in benchmarks/bench_covariance.py), with the same decisions: features
are compared as float32 as scikit-learn does, and each float64 threshold is stored as the
largest float32 not above it, which gives exactly the same ``x <= threshold`` outcome for
every float32 ``x``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numba
import numpy as np
from numpy.typing import NDArray

from semantic3d.core.atomic import row_workers, take_row_block
from semantic3d.core.errors import ShapeError

_BLOCK_ROWS = 256
_LEAF = np.uint32(0xFFFFFFFF)
"""``left`` of a leaf."""


@dataclass(frozen=True, slots=True)
class CompiledForest:
    """The trees of a fitted forest as flat arrays.

    Nodes of all trees are numbered consecutively; child indices are absolute. A leaf has
    ``left == 2**32 - 1`` and ``right`` = its row in ``leaf_values``.

    Attributes:
        feature: ``(n_nodes,)`` uint32 column tested at each node.
        threshold: ``(n_nodes,)`` float32 go left when ``x <= threshold``.
        left: ``(n_nodes,)`` uint32 left child, ``2**32 - 1`` at leaves.
        right: ``(n_nodes,)`` uint32 right child, or the leaf row at leaves.
        roots: ``(n_trees,)`` uint32 index of each tree's root.
        leaf_values: ``(n_leaves, n_classes)`` float64 class probabilities of each leaf.
        n_features: number of input columns.
    """

    feature: NDArray[np.uint32]
    threshold: NDArray[np.float32]
    left: NDArray[np.uint32]
    right: NDArray[np.uint32]
    roots: NDArray[np.uint32]
    leaf_values: NDArray[np.float64]
    n_features: int

    @property
    def n_classes(self) -> int:
        """Number of classes."""
        return int(self.leaf_values.shape[1])

    def predict_proba(self, features: NDArray[np.float32]) -> NDArray[np.float64]:
        """Mean leaf probabilities over the trees, ``(n_rows, n_classes)`` float64.

        The rows must be finite (the feature kernels and
        :meth:`CompiledClassifier.predict_proba` see to it)."""
        x = _writable(np.ascontiguousarray(features, dtype=np.float32))
        if x.ndim != 2 or x.shape[1] != self.n_features:
            raise ShapeError(f"features: expected (n, {self.n_features}), found {x.shape}")
        out = np.zeros((x.shape[0], self.n_classes), np.float64)
        if x.shape[0] == 0:
            return out
        feature, threshold, child, leaf_row, roots, depth = _walk_layout(
            _writable(self.feature),
            _writable(self.threshold),
            _writable(self.left),
            _writable(self.right),
            _writable(self.roots),
        )
        leaf_values = _writable(self.leaf_values)
        _predict_kernel(
            x,
            feature,
            threshold,
            child,
            leaf_row,
            roots,
            depth,
            leaf_values,
            out,
            numba.get_num_threads(),
        )
        return out


@dataclass(frozen=True, slots=True)
class CompiledClassifier:
    """A fitted :class:`~semantic3d.baselines.covariance.estimator.CovarianceClassifier`
    reduced to what prediction needs, with no scikit-learn object inside.

    Model files hold this instead of the estimator (:meth:`CovarianceClassifier.compact`):
    loading one to predict then imports no scikit-learn (~0.9 s of every ``predict``
    command's start) and the file is smaller. Its ``predict_proba`` and ``predict`` give
    the estimator's results.

    Attributes:
        classes_: ``(n_classes,)`` class labels (label values).
        compiled_: the flattened trees.
        feature_importances_: ``(n_features,)`` the fitted forest's impurity-based
            importances.
        params: the estimator's parameters (``get_params()``).
    """

    classes_: NDArray[Any]
    compiled_: CompiledForest
    feature_importances_: NDArray[np.float64]
    params: dict[str, Any]

    @property
    def n_features_in_(self) -> int:
        """Number of feature columns."""
        return self.compiled_.n_features

    def predict_proba(self, X: NDArray[Any]) -> NDArray[np.float64]:
        """``(n_rows, n_classes)`` class probabilities (columns follow ``classes_``)."""
        rows = np.asarray(X, dtype=np.float32)
        if rows.ndim != 2 or not np.isfinite(rows).all():
            raise ShapeError(
                f"features: expected (n, {self.n_features_in_}) finite values, found "
                f"{rows.shape if rows.ndim != 2 else 'NaN or infinite values'}"
            )
        return self.compiled_.predict_proba(rows)

    def predict(self, X: NDArray[Any]) -> NDArray[Any]:
        """The most probable class of every row."""
        result: NDArray[Any] = self.classes_[np.argmax(self.predict_proba(X), axis=1)]
        return result


def _writable(array: NDArray[Any]) -> NDArray[Any]:
    """``array``, copied when read-only (a memory map, a buffer from another process).

    The kernel is compiled for writable arrays only: read-only ones would be another
    compilation (seconds) on first use, far more than the copy.
    """
    return array if array.flags.writeable else np.array(array)


def compile_forest(estimators: list[Any], *, n_features: int) -> CompiledForest:
    """Flatten fitted ``DecisionTreeClassifier`` objects (one output) into a :class:`CompiledForest`."""
    parts: dict[str, list[NDArray[Any]]] = {"feature": [], "threshold": [], "left": [], "right": []}
    leaf_parts, roots = [], []
    node_offset = 0
    leaf_offset = 0
    for estimator in estimators:
        tree = estimator.tree_
        if tree.n_outputs != 1:
            raise ShapeError(f"compiled forest: expected one output, found {tree.n_outputs}")
        left = tree.children_left.astype(np.int64)
        right = tree.children_right.astype(np.int64)
        is_leaf = left == -1
        n = left.size
        leaf_rank = np.cumsum(is_leaf) - 1 + leaf_offset
        parts["feature"].append(np.where(is_leaf, 0, tree.feature))
        parts["threshold"].append(_float32_floor(tree.threshold))
        parts["left"].append(np.where(is_leaf, int(_LEAF), left + node_offset))
        parts["right"].append(np.where(is_leaf, leaf_rank, right + node_offset))
        values = tree.value[is_leaf, 0, :].astype(np.float64)
        totals = values.sum(axis=1, keepdims=True)
        leaf_parts.append(values / np.where(totals == 0.0, 1.0, totals))
        roots.append(node_offset)
        node_offset += n
        leaf_offset += int(is_leaf.sum())
    if node_offset >= int(_LEAF) or leaf_offset >= int(_LEAF):
        raise ShapeError(f"compiled forest: {node_offset} nodes exceed the uint32 node index")
    return CompiledForest(
        feature=np.concatenate(parts["feature"]).astype(np.uint32),
        threshold=np.concatenate(parts["threshold"]).astype(np.float32),
        left=np.concatenate(parts["left"]).astype(np.uint32),
        right=np.concatenate(parts["right"]).astype(np.uint32),
        roots=np.asarray(roots, np.uint32),
        leaf_values=np.concatenate(leaf_parts),
        n_features=n_features,
    )


def _float32_floor(thresholds: NDArray[np.float64]) -> NDArray[np.float32]:
    """The largest float32 ``<=`` each threshold (so ``x32 <= t32`` iff ``x32 <= t64``)."""
    rounded = thresholds.astype(np.float32)
    too_high = rounded.astype(np.float64) > thresholds
    rounded[too_high] = np.nextafter(rounded[too_high], np.float32(-np.inf))
    return rounded


@numba.njit(cache=True, nogil=True)
def _walk_layout(
    feature: NDArray[np.uint32],
    threshold: NDArray[np.float32],
    left: NDArray[np.uint32],
    right: NDArray[np.uint32],
    roots: NDArray[np.uint32],
) -> tuple[NDArray[Any], ...]:  # pragma: no cover - compiled
    """The trees renumbered for :func:`_predict_kernel` (about a millisecond per 100 k nodes).

    Each tree in breadth-first order, so that a node's two children are neighbours
    (``child`` and ``child + 1``) and the walk needs no branch: ``node = child[node] +
    (x > threshold)``. A leaf points to itself with an infinite threshold, so a walk of the
    tree's depth ends at the row's leaf however shallow it is; ``leaf_row`` is its row of
    ``leaf_values`` and ``depth`` the depth of every tree.
    """
    n_nodes = feature.size
    n_trees = roots.size
    new_feature = np.empty(n_nodes, np.uint32)
    new_threshold = np.empty(n_nodes, np.float32)
    child = np.empty(n_nodes, np.uint32)
    leaf_row = np.zeros(n_nodes, np.uint32)
    new_roots = np.empty(n_trees, np.uint32)
    depth = np.zeros(n_trees, np.int64)
    order = np.empty(n_nodes, np.uint32)  # old node at each new position
    level = np.empty(n_nodes, np.int64)
    end = 0
    for t in range(n_trees):
        new_roots[t] = end
        order[end] = roots[t]
        level[end] = 0
        end += 1
        position = new_roots[t]
        while position < end:
            old = order[position]
            depth[t] = max(depth[t], level[position])
            if left[old] == _LEAF:
                new_feature[position] = 0
                new_threshold[position] = np.inf
                child[position] = position
                leaf_row[position] = right[old]
            else:
                new_feature[position] = feature[old]
                new_threshold[position] = threshold[old]
                child[position] = end
                order[end] = left[old]
                order[end + 1] = right[old]
                level[end] = level[end + 1] = level[position] + 1
                end += 2
            position += 1
    return new_feature, new_threshold, child, leaf_row, new_roots, depth


_WALKERS = 16
"""Rows that walk a tree together."""


# Hand-written hot path: per-point classification of whole scans (see the module docstring).
# Tree-major inside a block of rows keeps one tree's nodes and the block's features in
# cache; 16 rows walk the tree in lock step, for the tree's depth, without a branch, so their
# dependent loads overlap and no unpredictable left/right branch stalls the pipeline.
# Measured on Oakland features (50 trees, 183 k nodes, mean leaf depth 14, max 20; one
# 96 k-row scan): 108 ms of CPU against 205 ms for the former walk (four rows, stopping at
# each leaf, a branch per node) and ~2x that for scikit-learn's predict_proba.
@numba.njit(cache=True, nogil=True, parallel=True)
def _predict_kernel(
    x: NDArray[np.float32],
    feature: NDArray[np.uint32],
    threshold: NDArray[np.float32],
    child: NDArray[np.uint32],
    leaf_row: NDArray[np.uint32],
    roots: NDArray[np.uint32],
    depth: NDArray[np.int64],
    leaf_values: NDArray[np.float64],
    out: NDArray[np.float64],
    n_threads: int,
) -> None:  # pragma: no cover - compiled
    n_rows = x.shape[0]
    n_trees = roots.size
    n_classes = leaf_values.shape[1]
    taken = np.zeros(1, np.int64)  # blocks of rows taken as threads come free
    for _worker in numba.prange(row_workers(n_threads, n_rows, _BLOCK_ROWS)):
        while True:
            begin, end = take_row_block(taken, n_rows, _BLOCK_ROWS)
            if begin >= end:
                break
            nodes = np.empty(_WALKERS, np.uint32)
            for t in range(n_trees):
                root = roots[t]
                steps = depth[t]
                row = begin
                while row + _WALKERS <= end:
                    for r in range(_WALKERS):  # constant trip counts: unrolled
                        nodes[r] = root
                    for _ in range(steps):
                        for r in range(_WALKERS):
                            node = nodes[r]
                            nodes[r] = child[node] + np.uint32(
                                x[row + r, feature[node]] > threshold[node]
                            )
                    for r in range(_WALKERS):
                        leaf = leaf_row[nodes[r]]
                        for c in range(n_classes):
                            out[row + r, c] += leaf_values[leaf, c]
                    row += _WALKERS
                while row < end:  # the block's last rows, one at a time
                    node = root
                    for _ in range(steps):
                        node = child[node] + np.uint32(x[row, feature[node]] > threshold[node])
                    leaf = leaf_row[node]
                    for c in range(n_classes):
                        out[row, c] += leaf_values[leaf, c]
                    row += 1
            for row in range(begin, end):
                for c in range(n_classes):
                    out[row, c] /= n_trees
