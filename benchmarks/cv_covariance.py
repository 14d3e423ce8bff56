"""Leave-scans-out cross-validation of the covariance baseline's levers on CMU Oakland.

Estimates how a configuration does on scans it has never seen: the 10 Oakland scans
(Munoz et al., CVPR 2009) are split into 5 folds of 2 whole scans (the assignment drawn
per seed); each fold is labelled by a model trained on the other 8 scans only, and the
confusion matrix is pooled over all points of all 10 scans, so every point is scored once
by a model that never saw its scan. Repeated over ``--seeds`` (fold assignment, training
sample and classifier seed change together); the table gives mean ± standard deviation
over seeds, per-class IoU means and the cost of each lever in feature points/s.

Levers (``--levers``, comma separated; default all):

- ``knn-height``: the pyramid's covariance features with the old height columns of the
  k nearest neighbours (the default before the cylinders);
- ``cylinders``: + height features of vertical cylinders per level (the paper's);
- ``cylinders-only``: cylinders, without the k-NN height columns;
- ``dtm``: + height above a terrain model (lowest point per 2 m cell, interpolated);
- ``more-points``: 3x the points per class;
- ``weights``: a uniform sample of the same size, balanced by class weights instead;
- ``hgb``: scikit-learn's HistGradientBoostingClassifier instead of the forest;
- ``smooth``: class probabilities mixed with the mean of their level-3 pyramid voxel;
- ``jakteristics``: the peer pipeline (jakteristics' 27 features at 4 radii + z above the
  scan's lowest point + a scikit-learn forest), test points subsampled 1 in 5;
- ``default``: the library default features (k-NN height + ``cylinder_below``), and on
  them: ``default-smooth-3`` / ``-2-4`` / ``-4-6`` (probabilities mixed with their voxel
  means at those levels), ``default-crf`` (alpha-expansion of a Potts energy on the 8
  nearest level-0 voxels, 3 sweeps; ``-1sweep``: 1, as the library; ``-wide``: weights
  2 to 32; ``-4``: weight 4 fixed; ``-4-positions``: weight 4 on a k-NN graph searched
  over the rows' point centroids, the library's until 2026-11-25 (the others take the
  features' own level-0 k-NN, cut at the prediction tiles, as ``predict`` does);
  ``-k4`` / ``-k6``: a graph of the 4 / 6 nearest voxels, weights 2 to 16), ``default-smooth-crf`` (levels 4-6 smoothing, then
  the graph cut), ``lgbm`` / ``lgbm-crf`` (LightGBM), ``hgb-es``
  (HistGradientBoosting), ``scan-norm`` (every column standardised per scan),
  ``default-dtm`` (+ height above a terrain model), ``no-scale-columns`` (without the
  columns measured in metres: sum of eigenvalues, moments, k-NN z-range and height above).

Nothing is tuned on a fold's test scans: where a lever has a free weight (smoothing,
Potts) or a number of boosting rounds (early stopping on log-loss), it is chosen per
fold on an *inner split* of the fold's training scans (a model fitted on 6 of them
labels the other 2), then the model is refitted on all 8. Levers that differ only in the
context step share their models (one run scores them all on the same predictions).

``--cost`` instead times end-to-end prediction with the library's context step off and
on (``benchmarks/out/context_cost.json``).

Keep runs small on a shared machine: ``--points-per-class`` and ``--trees`` set the size.
Usage: ``python benchmarks/cv_covariance.py --levers cylinders,hgb --seeds 0,1,2``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from semantic3d.baselines.covariance.config import CovarianceConfig
from semantic3d.baselines.covariance.context import (
    label_rows_by_group,
    row_centroids,
    smooth_probabilities,
)
from semantic3d.baselines.covariance.estimator import CovarianceClassifier
from semantic3d.baselines.covariance.model import point_tiles
from semantic3d.core import CLASSES, PointCloud
from semantic3d.features import FeatureConfig, build_cloud_pyramid, compute_multiscale_features
from semantic3d.features.names import CYLINDER_FEATURES
from semantic3d.features.neighbourhoods import LevelIndex
from semantic3d.io.ascii import read_ascii_points
from semantic3d.metrics import ConfusionMatrix

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "oakland"
OUT = ROOT / "benchmarks" / "out"

KNN_HEIGHT = FeatureConfig(cylinders=False)
CYLINDERS = dataclasses.replace(
    KNN_HEIGHT, cylinders=True, spherical_height=True, cylinder_features=CYLINDER_FEATURES
)
CYLINDERS_ONLY = dataclasses.replace(CYLINDERS, spherical_height=False)
DEFAULT = FeatureConfig()  # k-NN height + cylinder_below (the library default)

SMOOTH_WEIGHTS = (0.0, 0.25, 0.5, 0.75, 0.9)
"""Mixing weights of ``smooth`` levers, chosen per fold on the inner split."""
POTTS_WEIGHTS = (0.0, 0.5, 1.0, 2.0, 4.0, 8.0)
"""Pairwise weights of ``crf`` levers, chosen per fold on the inner split."""


@dataclass(frozen=True)
class Lever:
    """One configuration to cross-validate."""

    features: FeatureConfig | None  # None: the jakteristics peer
    classifier: str = "forest"  # forest | hgb
    sampling: str = "balanced"  # balanced | weights
    points_factor: float = 1.0
    dtm: bool = False
    trees: int | None = None  # None: --trees
    max_depth: int | None = 20
    drop: tuple[str, ...] = ()  # feature names (any level) left out of the classifier
    post: str = "none"  # none | smooth | crf | smooth-crf: context on the probabilities
    sweeps: int = 3  # alpha-expansion passes over the classes
    smooth_weight: float = 0.75  # fixed smoothing weight of `smooth-crf`
    weights: tuple[float, ...] = ()  # the context weights to choose from (default grid)
    smooth_levels: tuple[int, ...] = ()  # levels whose voxel means `smooth` mixes in
    scan_norm: bool = False  # standardise every column per scan (mean 0, std 1)
    exclude: tuple[str, ...] = ()  # feature names (any level) dropped by prefix match
    neighbours: int = 8  # k of the context step's nearest-neighbour graph
    graph: str = "features"  # features: the level-0 k-NN of the features; positions: a
    # k-NN search over the rows' point centroids (the library's graph until 2026-11-25)

    @property
    def training_key(self) -> tuple[Any, ...]:
        """Levers with equal keys share their models (they differ only in `post`)."""
        return dataclasses.astuple(
            dataclasses.replace(
                self,
                post="none",
                smooth_levels=(),
                sweeps=3,
                smooth_weight=0.75,
                weights=(),
                neighbours=8,
                graph="features",
            )
        )


LEVERS: dict[str, Lever] = {
    "knn-height": Lever(KNN_HEIGHT),
    "cylinders": Lever(CYLINDERS),
    "cylinders-only": Lever(CYLINDERS_ONLY),
    "dtm": Lever(CYLINDERS, dtm=True),
    "more-points": Lever(CYLINDERS, points_factor=3.0),
    "weights": Lever(CYLINDERS, sampling="weights"),
    "hgb": Lever(CYLINDERS, classifier="hgb"),
    "smooth": Lever(CYLINDERS, post="smooth", smooth_levels=(3,)),
    "jakteristics": Lever(None),
    "radius-4": Lever(dataclasses.replace(CYLINDERS, cylinder_radius_voxels=4.0)),
    "hgb-weights": Lever(CYLINDERS, classifier="hgb", sampling="weights"),
    "forest-100": Lever(CYLINDERS, trees=100, max_depth=None),
    "cylinders-below": Lever(
        CYLINDERS, drop=("cylinder_range", "cylinder_above", "cylinder_points")
    ),
    # On the default feature set (k-NN height + cylinder_below); inner-split selection.
    "default": Lever(DEFAULT),
    "default-smooth-3": Lever(DEFAULT, post="smooth", smooth_levels=(3,)),
    "default-smooth-2-4": Lever(DEFAULT, post="smooth", smooth_levels=(2, 3, 4)),
    "default-smooth-4-6": Lever(DEFAULT, post="smooth", smooth_levels=(4, 5, 6)),
    "default-crf": Lever(DEFAULT, post="crf"),
    "default-crf-1sweep": Lever(DEFAULT, post="crf", sweeps=1),
    "default-crf-wide": Lever(DEFAULT, post="crf", sweeps=1, weights=(2.0, 4.0, 8.0, 16.0, 32.0)),
    "default-crf-4": Lever(DEFAULT, post="crf", sweeps=1, weights=(4.0,)),
    "default-crf-4-positions": Lever(
        DEFAULT, post="crf", sweeps=1, weights=(4.0,), graph="positions"
    ),
    "default-crf-k4": Lever(
        DEFAULT, post="crf", sweeps=1, weights=(2.0, 4.0, 8.0, 16.0), neighbours=4
    ),
    "default-crf-k6": Lever(
        DEFAULT, post="crf", sweeps=1, weights=(2.0, 4.0, 8.0, 16.0), neighbours=6
    ),
    "default-smooth-crf": Lever(DEFAULT, post="smooth-crf", smooth_levels=(4, 5, 6)),
    "lgbm": Lever(DEFAULT, classifier="lgbm"),
    "lgbm-crf": Lever(DEFAULT, classifier="lgbm", post="crf", sweeps=1),
    "scan-norm-crf": Lever(DEFAULT, scan_norm=True, post="crf", sweeps=1),
    "default-dtm-crf": Lever(DEFAULT, dtm=True, post="crf", sweeps=1),
    "no-scale-columns-crf": Lever(
        DEFAULT,
        exclude=("sum_of_eigenvalues", "moment", "vertical_range", "height_above"),
        post="crf",
        sweeps=1,
    ),
    "hgb-es": Lever(DEFAULT, classifier="hgb-es"),
    "scan-norm": Lever(DEFAULT, scan_norm=True),
    "default-dtm": Lever(DEFAULT, dtm=True),
    "no-scale-columns": Lever(
        DEFAULT, exclude=("sum_of_eigenvalues", "moment", "vertical_range", "height_above")
    ),
}


@dataclass
class Scan:
    name: str
    cloud: PointCloud
    labels: NDArray[np.uint8]


@dataclass
class ScanRows:
    """Feature rows of every point of one scan (voxel rows + the row of each point)."""

    values: NDArray[np.float32]
    point_row: NDArray[np.int64]
    ancestors: dict[int, NDArray[np.int64]]


def load_scans(folder: Path) -> list[Scan]:
    scans = []
    for path in sorted(folder.glob("*.txt")):
        cloud = read_ascii_points(path, labels_path=path.with_suffix(".labels"))
        assert cloud.labels is not None
        scans.append(Scan(path.stem, cloud, cloud.labels))
    return scans


def terrain_height(
    xyz: NDArray[np.float64], queries: NDArray[np.float64], cell_m: float = 2.0
) -> NDArray[np.float32]:
    """Height of ``queries`` above a terrain model of ``xyz``: the lowest point of every
    ``cell_m`` XY cell (empty cells take the nearest cell's), bilinearly interpolated."""
    from scipy import ndimage

    low = xyz[:, :2].min(axis=0)
    cells = np.floor((xyz[:, :2] - low) / cell_m).astype(np.int64)
    shape = cells.max(axis=0) + 1
    grid = np.full(shape, np.inf)
    np.minimum.at(grid, (cells[:, 0], cells[:, 1]), xyz[:, 2])
    empty = ~np.isfinite(grid)
    if empty.any():
        _, (ix, iy) = ndimage.distance_transform_edt(empty, return_indices=True)
        grid = grid[ix, iy]
    coords = ((queries[:, :2] - low) / cell_m - 0.5).T
    ground = ndimage.map_coordinates(grid, coords, order=1, mode="nearest")
    return (queries[:, 2] - ground).astype(np.float32)


def our_rows(scan: Scan, lever: Lever) -> tuple[ScanRows, float]:
    assert lever.features is not None
    started = time.perf_counter()
    table = compute_multiscale_features(scan.cloud, config=lever.features)
    values = table.values
    if lever.dtm:
        pyramid = build_cloud_pyramid(scan.cloud, config=lever.features)
        voxels = pyramid.levels[0].xyz + pyramid.origin
        extra = terrain_height(scan.cloud.xyz, voxels)[:, None]
        values = np.hstack([values, extra])
    if lever.scan_norm:
        spread = values.std(axis=0)
        values = ((values - values.mean(axis=0)) / np.where(spread > 0, spread, 1)).astype(
            np.float32
        )
    return ScanRows(values, table.point_row, {}), time.perf_counter() - started


_CONTEXT: dict[tuple[str, int], Any] = {}


def ancestors_of(scan: Scan, features: FeatureConfig, level: int) -> NDArray[np.int64]:
    key = (scan.name, level)
    if key not in _CONTEXT:
        _CONTEXT[key] = build_cloud_pyramid(scan.cloud, config=features).ancestors(level)
    result: NDArray[np.int64] = _CONTEXT[key]
    return result


def graph_of(
    scan: Scan, features: FeatureConfig
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float64]]:
    """What ``predict`` builds the context graph of a scan labelled whole from: every
    level-0 voxel's canonical k-NN (the features' own, :attr:`FeatureTable.neighbours`),
    the prediction tile of every row (pairs across tiles are dropped) and, for the
    ``positions`` graph, the rows' point centroids (float32 positions, as predict keeps)."""
    key = (scan.name, -1)
    if key not in _CONTEXT:
        pyramid = build_cloud_pyramid(scan.cloud, config=features)
        level = pyramid.levels[0]
        lists = LevelIndex(level.xyz, level.keys).query(level.xyz, k=features.k_neighbours)
        tiles = np.zeros(level.n_voxels, np.int64)
        config = dataclasses.replace(CovarianceConfig(), features=features)
        tiles[pyramid.point_voxel] = point_tiles(
            scan.cloud.xyz, origin=pyramid.origin, config=config
        )
        relative = (scan.cloud.xyz - pyramid.origin).astype(np.float32)
        centroids = row_centroids(relative, pyramid.point_voxel, level.n_voxels)
        _CONTEXT[key] = (lists.indices.astype(np.int64), tiles, centroids)
    result: tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float64]] = _CONTEXT[key]
    return result


JAK_RADII = (0.25, 0.5, 1.0, 2.0)


def jakteristics_rows(scan: Scan, points: NDArray[np.int64]) -> NDArray[np.float32]:
    import jakteristics

    xyz = scan.cloud.xyz - scan.cloud.xyz.min(axis=0)
    tree = jakteristics.cKDTree(xyz)
    parts = [
        jakteristics.compute_features(
            xyz[points], search_radius=r, kdtree=tree, num_threads=-1, max_k_neighbors=2000
        )
        for r in JAK_RADII
    ]
    parts.append(xyz[points, 2:3])
    return np.nan_to_num(np.hstack(parts).astype(np.float32))


def draw_training(
    scans: list[Scan], train: list[int], lever: Lever, per_class: int, rng: np.random.Generator
) -> dict[int, NDArray[np.int64]]:
    """Point indices per training scan: class-balanced, or uniform (balanced by weights)."""
    per_class = int(per_class * lever.points_factor)
    labels = np.concatenate([scans[i].labels for i in train])
    owner = np.concatenate([np.full(scans[i].labels.size, i) for i in train])
    offset = np.concatenate([np.arange(scans[i].labels.size) for i in train])
    labelled = np.flatnonzero(labels > 0)
    if lever.sampling == "weights":
        n_classes = len(np.unique(labels[labelled]))
        picks = rng.choice(labelled, size=min(labelled.size, per_class * n_classes), replace=False)
    else:
        chosen = []
        for value in np.unique(labels[labelled]):
            members = labelled[labels[labelled] == value]
            chosen.append(rng.choice(members, size=min(per_class, members.size), replace=False))
        picks = np.concatenate(chosen)
    return {i: np.sort(offset[picks[owner[picks] == i]]) for i in train}


def make_classifier(lever: Lever, trees: int, seed: int, n_iter: int | None = None) -> Any:
    weight = "balanced" if lever.sampling == "weights" else None
    if lever.classifier == "hgb":
        from sklearn.ensemble import HistGradientBoostingClassifier

        return HistGradientBoostingClassifier(
            max_iter=200, learning_rate=0.1, class_weight=weight, random_state=seed
        )
    if lever.classifier == "hgb-es":
        from sklearn.ensemble import HistGradientBoostingClassifier

        return HistGradientBoostingClassifier(
            max_iter=n_iter or BOOST_MAX_ITER,
            learning_rate=0.1,
            max_leaf_nodes=31,
            min_samples_leaf=20,
            l2_regularization=1.0,
            early_stopping=False,
            class_weight="balanced",
            random_state=seed,
        )
    if lever.classifier == "lgbm":
        import lightgbm

        return lightgbm.LGBMClassifier(
            n_estimators=n_iter or BOOST_MAX_ITER,
            learning_rate=0.1,
            num_leaves=31,
            min_child_samples=20,
            subsample=0.8,
            subsample_freq=1,
            colsample_bytree=0.5,
            reg_lambda=1.0,
            class_weight="balanced",
            n_jobs=2,
            random_state=seed,
            verbose=-1,
        )
    return CovarianceClassifier(
        n_estimators=lever.trees or trees,
        max_depth=lever.max_depth,
        class_weight=weight,
        n_jobs=-1,
        random_state=seed,
    )


BOOST_MAX_ITER = 400
"""Most boosting rounds; early stopping on the inner split picks fewer."""


def best_iteration(
    lever: Lever, trees: int, seed: int, x: Any, y: Any, x_val: Any, y_val: Any
) -> tuple[Any, int]:
    """Fit a booster on the inner training scans; the round with the lowest log-loss on the
    inner validation scans (patience 30 for LightGBM, the whole path for scikit-learn)."""
    from sklearn.metrics import log_loss

    model = make_classifier(lever, trees, seed)
    if lever.classifier == "lgbm":
        import lightgbm

        model.fit(
            x,
            y,
            eval_set=[(x_val, y_val)],
            callbacks=[lightgbm.early_stopping(30, verbose=False)],
        )
        return model, max(1, int(model.best_iteration_ or BOOST_MAX_ITER))
    model.fit(x, y)
    losses = [log_loss(y_val, p, labels=model.classes_) for p in model.staged_predict_proba(x_val)]
    return model, int(np.argmin(losses)) + 1


def scores_of(truth: list[NDArray[np.uint8]], predicted: list[NDArray[np.uint8]]) -> Any:
    matrix = ConfusionMatrix()
    for t, p in zip(truth, predicted, strict=True):
        matrix.update(t, p)
    return matrix.compute_scores()


def apply_post(
    scan: Scan, lever: Lever, proba: NDArray[np.float64], weight: float
) -> NDArray[np.int64]:
    """Column indices of every row after the lever's context step."""
    assert lever.features is not None
    if lever.post == "smooth" and weight > 0:
        levels = [ancestors_of(scan, lever.features, level) for level in lever.smooth_levels]
        proba = smooth_probabilities(proba, levels, weight=weight)
    if lever.post == "smooth-crf":
        levels = [ancestors_of(scan, lever.features, level) for level in lever.smooth_levels]
        proba = smooth_probabilities(proba, levels, weight=lever.smooth_weight)
    if lever.post in ("crf", "smooth-crf") and weight > 0:
        lists, tiles, centroids = graph_of(scan, lever.features)
        return label_rows_by_group(
            proba,
            centroids,
            tiles,
            potts_weight=weight,
            n_neighbours=lever.neighbours,
            max_sweeps=lever.sweeps,
            neighbours=lists if lever.graph == "features" else None,
        )
    return np.argmax(proba, axis=1)


def post_weights(lever: Lever) -> tuple[float, ...]:
    if lever.weights:
        return lever.weights
    return {"smooth": SMOOTH_WEIGHTS, "crf": POTTS_WEIGHTS, "smooth-crf": POTTS_WEIGHTS}.get(
        lever.post, (0.0,)
    )


_ROWS: dict[Any, tuple[list[ScanRows], float]] = {}
"""Feature rows of the last feature set (levers differing only in training reuse them)."""


def cross_validate(
    scans: list[Scan],
    group: list[tuple[str, Lever]],
    *,
    seeds: list[int],
    per_class: int,
    trees: int,
    n_folds: int,
) -> dict[str, dict[str, Any]]:
    """Cross-validate levers that share their training (differing only in ``post``)."""
    lever = group[0][1]
    rows: list[ScanRows] = []
    feature_s = 0.0
    if lever.features is not None:
        key = (lever.features, lever.dtm, lever.scan_norm)
        if key not in _ROWS:
            _ROWS.clear()  # one feature set held at a time
            timed = [our_rows(scan, lever) for scan in scans]
            _ROWS[key] = ([r for r, _ in timed], sum(t for _, t in timed))
        rows, feature_s = _ROWS[key]
        dropped = lever.drop + lever.exclude
        if dropped:
            names = list(lever.features.feature_names)
            keep = [
                i
                for i, n in enumerate(names)
                if n.split("@")[0] not in lever.drop
                and not n.split("@")[0].startswith(lever.exclude or ("\0",))
            ]
            rows = [ScanRows(r.values[:, keep], r.point_row, r.ancestors) for r in rows]
    needs_inner = lever.classifier in ("lgbm", "hgb-es") or any(
        len(post_weights(lv)) > 1 for _, lv in group
    )
    n_points = sum(s.labels.size for s in scans)
    per_lever: dict[str, dict[str, Any]] = {
        name: {"miou": [], "oa": [], "iou": [], "post_s": 0.0, "chosen": []} for name, _ in group
    }
    fit_s, predict_s, rounds = 0.0, 0.0, []
    for seed in seeds:
        rng = np.random.default_rng(seed)
        order = rng.permutation(len(scans))
        truth: list[NDArray[np.uint8]] = []
        predicted: dict[str, list[NDArray[np.uint8]]] = {name: [] for name, _ in group}
        for fold in range(n_folds):
            test = [int(i) for i in order[fold::n_folds]]
            train = [i for i in range(len(scans)) if i not in test]
            drawn = draw_training(scans, train, lever, per_class, rng)
            if lever.features is None:
                x = np.vstack([jakteristics_rows(scans[i], p) for i, p in drawn.items()])
            else:
                x = np.vstack([rows[i].values[rows[i].point_row[p]] for i, p in drawn.items()])
            y = np.concatenate([scans[i].labels[p] for i, p in drawn.items()])
            owner = np.concatenate([np.full(p.size, i) for i, p in drawn.items()])
            chosen_weight = {name: post_weights(lv)[0] for name, lv in group}
            n_iter = None
            started = time.perf_counter()
            if needs_inner:
                # Inner split: 2 of the training scans validate; never the fold's test scans.
                inner_rng = np.random.default_rng([seed, fold, 7])
                inner_val = [int(i) for i in inner_rng.choice(train, size=2, replace=False)]
                inside = ~np.isin(owner, inner_val)
                if lever.classifier in ("lgbm", "hgb-es"):
                    inner, n_iter = best_iteration(
                        lever, trees, seed, x[inside], y[inside], x[~inside], y[~inside]
                    )
                    rounds.append(n_iter)
                else:
                    inner = make_classifier(lever, trees, seed).fit(x[inside], y[inside])
                classes = np.asarray(inner.classes_, dtype=np.uint8)
                inner_proba = {i: inner.predict_proba(rows[i].values) for i in inner_val}
                for name, lv in group:
                    weights = post_weights(lv)
                    if len(weights) == 1:
                        continue
                    best = max(
                        weights,
                        key=lambda w, lv=lv: (
                            scores_of(
                                [scans[i].labels for i in inner_val],
                                [
                                    classes[apply_post(scans[i], lv, inner_proba[i], w)][
                                        rows[i].point_row
                                    ]
                                    for i in inner_val
                                ],
                            ).mean_iou
                        ),
                    )
                    chosen_weight[name] = best
                    per_lever[name]["chosen"].append(best)
            model = make_classifier(lever, trees, seed, n_iter).fit(x, y)
            fit_s += time.perf_counter() - started
            classes = np.asarray(model.classes_, dtype=np.uint8)
            for i in test:
                truth_i = scans[i].labels
                if lever.features is None:
                    points = np.arange(0, scans[i].labels.size, 5)
                    truth.append(truth_i[points])
                    predicted[group[0][0]].append(
                        model.predict(jakteristics_rows(scans[i], points)).astype(np.uint8)
                    )
                    continue
                truth.append(truth_i)
                started = time.perf_counter()
                proba = model.predict_proba(rows[i].values)
                predict_s += time.perf_counter() - started
                for name, lv in group:
                    started = time.perf_counter()
                    columns = apply_post(scans[i], lv, proba, chosen_weight[name])
                    per_lever[name]["post_s"] += time.perf_counter() - started
                    predicted[name].append(classes[columns][rows[i].point_row])
        for name, _ in group:
            scores = scores_of(truth, predicted[name])
            per_lever[name]["miou"].append(scores.mean_iou)
            per_lever[name]["oa"].append(scores.overall_accuracy)
            per_lever[name]["iou"].append(scores.iou)
            print(
                f"  {name} seed {seed}: mIoU {scores.mean_iou:.3f} "
                f"OA {scores.overall_accuracy:.3f}",
                flush=True,
            )
    results = {}
    n_scored = n_points * len(seeds)
    for name, lv in group:
        r = per_lever[name]
        results[name] = {
            "lever": name,
            "miou_mean": float(np.mean(r["miou"])),
            "miou_std": float(np.std(r["miou"])),
            "miou_per_seed": [float(v) for v in r["miou"]],
            "oa_mean": float(np.mean(r["oa"])),
            "oa_std": float(np.std(r["oa"])),
            "iou_mean": [None if np.isnan(v) else float(v) for v in np.nanmean(r["iou"], axis=0)],
            "feature_points_per_s": n_points / feature_s if feature_s else None,
            "classify_points_per_s": n_scored / predict_s if predict_s else None,
            "post_points_per_s": n_scored / r["post_s"] if r["post_s"] else None,
            "chosen_weights": r["chosen"],
            "boosting_rounds": rounds,
            "fit_s_per_fold": fit_s / (len(seeds) * n_folds),
            "seeds": seeds,
            "points_per_class": int(per_class * lv.points_factor),
            "trees": lv.trees or trees,
        }
    return results


def measure_context_cost(folder: Path, *, repeats: int = 3) -> dict[str, Any]:
    """End-to-end prediction (read ASCII, features, classify, context, write .labels) of
    Oakland aj and ak by a default model trained on the other 8 scans, with the context
    step off and on; runs interleaved, best of ``repeats``, wall and process CPU seconds."""
    import resource
    import tempfile

    from semantic3d.baselines.covariance.config import ContextConfig, CovarianceConfig
    from semantic3d.baselines.covariance.predict import predict_scan
    from semantic3d.baselines.covariance.training import (
        find_labelled_scans,
        train_covariance_model,
    )

    test = ["oakland_part2_aj", "oakland_part2_ak"]
    names = [p.stem for p in sorted(folder.glob("*.txt")) if p.stem not in test]
    config = CovarianceConfig(context=ContextConfig(potts_weight=4.0))
    model = train_covariance_model(find_labelled_scans(folder, names=names), config=config)
    variants = {
        "argmax": dataclasses.replace(
            model,
            config=dataclasses.replace(
                config, context=dataclasses.replace(config.context, potts_weight=0.0)
            ),
        ),
        "context": model,
    }

    def cpu() -> float:
        usage = resource.getrusage(resource.RUSAGE_SELF)
        return usage.ru_utime + usage.ru_stime

    best: dict[str, tuple[float, float]] = {}
    n_points = 0
    with tempfile.TemporaryDirectory() as scratch:
        for repeat in range(repeats):
            for name, variant in variants.items():
                wall, used, n_points = time.perf_counter(), cpu(), 0
                for scan in test:
                    run = predict_scan(
                        variant,
                        folder / f"{scan}.txt",
                        out_path=Path(scratch) / f"{name}{repeat}{scan}.labels",
                    )
                    n_points += run.n_points
                timing = (time.perf_counter() - wall, cpu() - used)
                best[name] = min(best.get(name, timing), timing)
    result = {
        name: {"wall_s": w, "cpu_s": c, "points_per_s": n_points / w}
        for name, (w, c) in best.items()
    }
    result["cpu_ratio"] = best["context"][1] / best["argmax"][1]
    result["potts_weight"] = config.context.potts_weight
    print(json.dumps(result, indent=2))
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--levers", default=",".join(LEVERS))
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--points-per-class", type=int, default=2000)
    parser.add_argument("--trees", type=int, default=30)
    parser.add_argument("--folds", type=int, default=5)
    parser.add_argument("--out", type=Path, default=OUT / "cv_covariance.json")
    parser.add_argument(
        "--cost", action="store_true", help="only time prediction with the context step off/on"
    )
    args = parser.parse_args()
    if not args.data.is_dir():
        sys.exit(f"{args.data}: the real samples are needed (../shared/data/oakland)")
    if args.cost:
        out = args.out.with_name("context_cost.json")
        out.write_text(json.dumps(measure_context_cost(args.data), indent=2) + "\n")
        return
    scans = load_scans(args.data)
    seeds = [int(s) for s in args.seeds.split(",")]
    results = json.loads(args.out.read_text()) if args.out.exists() else {}
    groups: dict[Any, list[tuple[str, Lever]]] = {}
    for name in args.levers.split(","):
        groups.setdefault(LEVERS[name].training_key, []).append((name, LEVERS[name]))
    for group in groups.values():
        print(f"== {', '.join(name for name, _ in group)}", flush=True)
        results.update(
            cross_validate(
                scans,
                group,
                seeds=seeds,
                per_class=args.points_per_class,
                trees=args.trees,
                n_folds=args.folds,
            )
        )
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(results, indent=2) + "\n")
    print_table(results)


def print_table(results: dict[str, Any]) -> None:
    short: Callable[[str], str] = lambda n: n[:9]  # noqa: E731
    print(
        f"\n{'lever':16s} {'mIoU':>13s} {'OA':>13s} {'feat. k pts/s':>13s} {'fit s':>6s}  ", end=""
    )
    print(" ".join(f"{short(c.name):>9s}" for c in CLASSES))
    for name, r in results.items():
        rate = r["feature_points_per_s"]
        print(
            f"{name:16s} {r['miou_mean']:.3f} ± {r['miou_std']:.3f} "
            f"{r['oa_mean']:.3f} ± {r['oa_std']:.3f} "
            f"{'' if rate is None else f'{rate / 1e3:.0f}':>13s} {r['fit_s_per_fold']:6.1f}  "
            + " ".join("      n/a" if v is None else f"{v:9.3f}" for v in r["iou_mean"])
        )


if __name__ == "__main__":
    main()
