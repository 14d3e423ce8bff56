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
- ``smooth``: class probabilities averaged with the mean of their level-3 pyramid voxel;
- ``jakteristics``: the peer pipeline (jakteristics' 27 features at 4 radii + z above the
  scan's lowest point + a scikit-learn forest), test points subsampled 1 in 5.

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

from semantic3d.baselines.covariance.estimator import CovarianceClassifier
from semantic3d.core import CLASSES, PointCloud
from semantic3d.features import FeatureConfig, build_cloud_pyramid, compute_multiscale_features
from semantic3d.features.names import CYLINDER_FEATURES
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


@dataclass(frozen=True)
class Lever:
    """One configuration to cross-validate."""

    features: FeatureConfig | None  # None: the jakteristics peer
    classifier: str = "forest"  # forest | hgb
    sampling: str = "balanced"  # balanced | weights
    points_factor: float = 1.0
    dtm: bool = False
    smooth_level: int | None = None
    trees: int | None = None  # None: --trees
    max_depth: int | None = 20
    drop: tuple[str, ...] = ()  # feature names (any level) left out of the classifier


LEVERS: dict[str, Lever] = {
    "knn-height": Lever(KNN_HEIGHT),
    "cylinders": Lever(CYLINDERS),
    "cylinders-only": Lever(CYLINDERS_ONLY),
    "dtm": Lever(CYLINDERS, dtm=True),
    "more-points": Lever(CYLINDERS, points_factor=3.0),
    "weights": Lever(CYLINDERS, sampling="weights"),
    "hgb": Lever(CYLINDERS, classifier="hgb"),
    "smooth": Lever(CYLINDERS, smooth_level=3),
    "jakteristics": Lever(None),
    "radius-4": Lever(dataclasses.replace(CYLINDERS, cylinder_radius_voxels=4.0)),
    "hgb-weights": Lever(CYLINDERS, classifier="hgb", sampling="weights"),
    "forest-100": Lever(CYLINDERS, trees=100, max_depth=None),
    "cylinders-below": Lever(
        CYLINDERS, drop=("cylinder_range", "cylinder_above", "cylinder_points")
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
    ancestors: dict[int, NDArray[np.int64]] = {}
    if lever.dtm or lever.smooth_level is not None:
        pyramid = build_cloud_pyramid(scan.cloud, config=lever.features)
        if lever.dtm:
            voxels = pyramid.levels[0].xyz + pyramid.origin
            extra = terrain_height(scan.cloud.xyz, voxels)[:, None]
            values = np.hstack([values, extra])
        if lever.smooth_level is not None:
            ancestors[lever.smooth_level] = pyramid.ancestors(lever.smooth_level)
    return ScanRows(values, table.point_row, ancestors), time.perf_counter() - started


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


def make_classifier(lever: Lever, trees: int, seed: int) -> Any:
    weight = "balanced" if lever.sampling == "weights" else None
    if lever.classifier == "hgb":
        from sklearn.ensemble import HistGradientBoostingClassifier

        return HistGradientBoostingClassifier(
            max_iter=200, learning_rate=0.1, class_weight=weight, random_state=seed
        )
    return CovarianceClassifier(
        n_estimators=lever.trees or trees,
        max_depth=lever.max_depth,
        class_weight=weight,
        n_jobs=-1,
        random_state=seed,
    )


def smooth(
    proba: NDArray[np.float64], ancestor: NDArray[np.int64], weight: float = 0.5
) -> NDArray[np.float64]:
    """Mix each row's probabilities with the mean over its pyramid voxel at a coarser level."""
    count = np.bincount(ancestor).astype(np.float64)
    means = (
        np.stack(
            [
                np.bincount(ancestor, proba[:, c], minlength=count.size)
                for c in range(proba.shape[1])
            ],
            axis=1,
        )
        / np.maximum(count, 1)[:, None]
    )
    result: NDArray[np.float64] = (1 - weight) * proba + weight * means[ancestor]
    return result


_ROWS: dict[Any, tuple[list[ScanRows], float]] = {}
"""Feature rows of the last feature set (levers differing only in training reuse them)."""


def cross_validate(
    scans: list[Scan],
    name: str,
    lever: Lever,
    *,
    seeds: list[int],
    per_class: int,
    trees: int,
    n_folds: int,
) -> dict[str, Any]:
    rows: list[ScanRows] = []
    feature_s = 0.0
    if lever.features is not None:
        key = (lever.features, lever.dtm, lever.smooth_level)
        if key not in _ROWS:
            _ROWS.clear()  # one feature set held at a time
            timed = [our_rows(scan, lever) for scan in scans]
            _ROWS[key] = ([r for r, _ in timed], sum(t for _, t in timed))
        rows, feature_s = _ROWS[key]
        if lever.drop:
            names = lever.features.feature_names
            keep = [i for i, n in enumerate(names) if n.split("@")[0] not in lever.drop]
            rows = [ScanRows(r.values[:, keep], r.point_row, r.ancestors) for r in rows]
    n_points = sum(s.labels.size for s in scans)
    miou, oa, ious, fit_s = [], [], [], 0.0
    for seed in seeds:
        rng = np.random.default_rng(seed)
        order = rng.permutation(len(scans))
        matrix = ConfusionMatrix()
        for fold in range(n_folds):
            test = [int(i) for i in order[fold::n_folds]]
            train = [i for i in range(len(scans)) if i not in test]
            drawn = draw_training(scans, train, lever, per_class, rng)
            if lever.features is None:
                x = np.vstack([jakteristics_rows(scans[i], p) for i, p in drawn.items()])
            else:
                x = np.vstack([rows[i].values[rows[i].point_row[p]] for i, p in drawn.items()])
            y = np.concatenate([scans[i].labels[p] for i, p in drawn.items()])
            started = time.perf_counter()
            model = make_classifier(lever, trees, seed).fit(x, y)
            fit_s += time.perf_counter() - started
            for i in test:
                if lever.features is None:
                    points = np.arange(0, scans[i].labels.size, 5)
                    predicted = model.predict(jakteristics_rows(scans[i], points))
                    matrix.update(scans[i].labels[points], predicted)
                    continue
                proba = model.predict_proba(rows[i].values)
                if lever.smooth_level is not None:
                    proba = smooth(proba, rows[i].ancestors[lever.smooth_level])
                row_labels = np.asarray(model.classes_)[np.argmax(proba, axis=1)]
                matrix.update(scans[i].labels, row_labels[rows[i].point_row].astype(np.uint8))
        scores = matrix.compute_scores()
        miou.append(scores.mean_iou)
        oa.append(scores.overall_accuracy)
        ious.append(scores.iou)
        print(f"  {name} seed {seed}: mIoU {scores.mean_iou:.3f} OA {scores.overall_accuracy:.3f}")
    result = {
        "lever": name,
        "miou_mean": float(np.mean(miou)),
        "miou_std": float(np.std(miou)),
        "oa_mean": float(np.mean(oa)),
        "oa_std": float(np.std(oa)),
        "iou_mean": [None if np.isnan(v) else float(v) for v in np.nanmean(ious, axis=0)],
        "feature_points_per_s": n_points / feature_s if feature_s else None,
        "fit_s_per_fold": fit_s / (len(seeds) * n_folds),
        "seeds": seeds,
        "points_per_class": int(per_class * lever.points_factor),
        "trees": lever.trees or trees,
    }
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
    args = parser.parse_args()
    if not args.data.is_dir():
        sys.exit(f"{args.data}: the real samples are needed (../shared/data/oakland)")
    scans = load_scans(args.data)
    seeds = [int(s) for s in args.seeds.split(",")]
    results = json.loads(args.out.read_text()) if args.out.exists() else {}
    for name in args.levers.split(","):
        print(f"== {name}")
        results[name] = cross_validate(
            scans,
            name,
            LEVERS[name],
            seeds=seeds,
            per_class=args.points_per_class,
            trees=args.trees,
            n_folds=args.folds,
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
