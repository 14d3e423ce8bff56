"""Training the covariance baseline: class-balanced sampling, features, forest, grid search.

Following Hackel et al. (2016), the forest is trained on a class-balanced sample: a fixed
number of labelled points per class, drawn uniformly over all training scans. Labels are
read first (cheap) to draw the sample; features are then computed only for the drawn
points, scan by scan, so memory stays bounded however many scans are used. The grid
search scores each hyper-parameter set by cross-validation with folds grouped by scan
(``GroupKFold``), so no scan is in both a training and a validation fold.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from semantic3d import __version__
from semantic3d.baselines.common.prediction import scans_at_once
from semantic3d.baselines.common.scans import LabelledScan, TrainingDataError, find_labelled_scans
from semantic3d.baselines.covariance.config import CovarianceConfig
from semantic3d.baselines.covariance.estimator import CovarianceClassifier
from semantic3d.baselines.covariance.model import CovarianceModel, GridSearchResult
from semantic3d.core.classes import N_CLASSES, class_by_value
from semantic3d.core.errors import DataFormatError, require
from semantic3d.core.threads import map_in_threads, thread_budget
from semantic3d.features.scan import iter_scan_features

__all__ = [
    "GridSearchResult",
    "ItemMapper",
    "LabelledScan",
    "RowsOfScan",
    "ScanRows",
    "TrainingDataError",
    "TrainingSet",
    "build_training_set",
    "count_scan_labels",
    "find_labelled_scans",
    "fit_model",
    "merge_scan_rows",
    "run_grid_search",
    "sample_training_points",
    "scan_training_rows",
    "train_covariance_model",
]

logger = logging.getLogger(__name__)

Progress = Callable[[str, int, int], None]
"""``progress(stage, done, total)``: called as scans are read and features computed."""


@dataclass(frozen=True, slots=True)
class TrainingSet:
    """Sampled training rows.

    Attributes:
        features: ``(n, n_features)`` float32.
        labels: ``(n,)`` uint8 label values.
        groups: ``(n,)`` int64 index of each row's scan in ``scan_names``.
        scan_names: the training scans.
        feature_names: column names.
        feature_time_s: time spent reading scans and computing features.
    """

    features: NDArray[np.float32]
    labels: NDArray[np.uint8]
    groups: NDArray[np.int64]
    scan_names: tuple[str, ...]
    feature_names: tuple[str, ...]
    feature_time_s: float

    def counts(self) -> dict[int, int]:
        """Rows per label value."""
        values, counts = np.unique(self.labels, return_counts=True)
        return {int(v): int(c) for v, c in zip(values, counts, strict=True)}


def sample_training_points(
    label_counts: NDArray[np.int64],
    *,
    points_per_class: int,
    classes: Sequence[int],
    seed: int,
) -> list[dict[int, NDArray[np.int64]]]:
    """Draw ``points_per_class`` points of each class uniformly over all scans.

    Args:
        label_counts: ``(n_scans, N_CLASSES + 1)`` points per scan and label value.
        points_per_class: draw size per class (all points when a class has fewer).
        classes: label values to draw.
        seed: random seed.

    Returns:
        Per scan, ``{label value: sorted ordinals among that scan's points of the class}``.
    """
    rng = np.random.default_rng(seed)
    n_scans = label_counts.shape[0]
    drawn: list[dict[int, NDArray[np.int64]]] = [{} for _ in range(n_scans)]
    for value in classes:
        per_scan = label_counts[:, value]
        total = int(per_scan.sum())
        size = min(points_per_class, total)
        picks = np.sort(rng.choice(total, size=size, replace=False))
        offsets = np.concatenate(([0], np.cumsum(per_scan)))
        for scan in range(n_scans):
            lo, hi = np.searchsorted(picks, offsets[scan : scan + 2])
            drawn[scan][value] = picks[lo:hi] - offsets[scan]
    return drawn


def count_scan_labels(scan: LabelledScan) -> NDArray[np.int64]:
    """``(N_CLASSES + 1,)`` points per label value; values above N_CLASSES are an error."""
    counts = np.zeros(N_CLASSES + 1, np.int64)
    seen = 0
    for chunk in scan.iter_labels():
        counts += np.bincount(chunk, minlength=256)[: N_CLASSES + 1]
        if chunk.size and int(chunk.max()) > N_CLASSES:
            line = seen + int(np.argmax(chunk > N_CLASSES)) + 1
            raise DataFormatError(
                f"expected label values 0..{N_CLASSES}, found {int(chunk.max())}",
                path=str(scan.labels_path or scan.points_path),
                line=line,
            )
        seen += chunk.size
    return counts


ScanRows = tuple[NDArray[np.int64], NDArray[np.float32], NDArray[np.uint8]]
"""One scan's sampled rows: ``(point_indices ascending, features, label values)``."""

RowsOfScan = Callable[[LabelledScan, NDArray[np.int64]], ScanRows]
"""``rows_of_scan(scan, select)``: the feature rows of the points ``select`` of ``scan``."""

ItemMapper = Callable[[Callable[[Any], Any], Sequence[Any]], Iterable[Any]]
"""``map_items(function, items)``: results in input order (e.g. a Dask cluster's map)."""


def build_training_set(
    scans: Sequence[LabelledScan],
    *,
    config: CovarianceConfig,
    progress: Progress | None = None,
    map_scans: ItemMapper | None = None,
    rows_of_scan: RowsOfScan | None = None,
) -> TrainingSet:
    """Sample training points class-balanced over ``scans`` and compute their features.

    Each scan's rows are in ascending point order whether the scan was described whole or
    tile by tile (tiled rows equal whole-scan rows), so the training set, and the forest
    fitted on it, do not depend on how the scan was cut or where it was described.

    Args:
        scans: the labelled training scans.
        config: sampling, feature and prediction (tiling) settings.
        progress: called as scans are described.
        map_scans: reads the scans' labels elsewhere (counting them, then finding the
            drawn points; e.g. on a Dask cluster) instead of one after another here.
        rows_of_scan: computes one scan's rows elsewhere (default
            :func:`scan_training_rows` here); same rows.
    """
    started = time.perf_counter()
    if not scans:
        raise TrainingDataError("training needs at least one labelled scan")
    mapper: ItemMapper = map_scans if map_scans is not None else _map_in_threads
    counts = np.stack(list(mapper(count_scan_labels, list(scans))))
    drawn = sample_training_points(
        counts,
        points_per_class=config.sampling.points_per_class,
        classes=_classes_to_draw(counts, scans, config),
        seed=config.sampling.seed,
    )
    selections = list(mapper(_drawn_point_indices, list(zip(scans, drawn, strict=True))))
    items = [(scan, select) for scan, select in zip(scans, selections, strict=True)]
    if rows_of_scan is not None:
        described: Iterable[ScanRows] = (
            rows_of_scan(scan, select) if select.size else _no_rows(select)
            for scan, select in items
        )
    else:  # scans described at the same time, each with a share of the thread budget
        budget = thread_budget()
        # as many at once as `predict --data` labels (memory: that many scans)
        n_at_once = scans_at_once(len(items))
        described = map_in_threads(
            partial(_scan_rows, config=config),
            items,
            n_threads=budget,  # the threads of all scans at once: a share each
            numba_threads_per_task=max(1, budget // n_at_once),
            max_pending=n_at_once,
            name="s3d-train-scan",
        )
    features, labels, groups = [], [], []
    for number, ((scan, select), (indices, rows, values)) in enumerate(
        zip(items, described, strict=True)
    ):
        if progress is not None:
            progress("features", number, len(scans))
        if select.size == 0:
            continue
        if not np.array_equal(indices, select):  # a broken rows_of_scan, never the data
            raise RuntimeError(f"{scan.name}: rows for {indices.size} of {select.size} points")
        features.append(rows)
        labels.append(values)
        groups.append(np.full(indices.size, number, np.int64))
        logger.info("%s: %d training points", scan.name, select.size)
    if progress is not None:
        progress("features", len(scans), len(scans))
    return TrainingSet(
        features=np.concatenate(features),
        labels=np.concatenate(labels),
        groups=np.concatenate(groups),
        scan_names=tuple(s.name for s in scans),
        feature_names=config.features.feature_names,
        feature_time_s=time.perf_counter() - started,
    )


def scan_training_rows(
    scan: LabelledScan,
    select: NDArray[np.int64],
    *,
    config: CovarianceConfig,
    workdir: str | Path | None = None,
) -> ScanRows:
    """Feature rows and labels of the points ``select`` (sorted, unique) of ``scan``, in
    ascending point order; the scan is described whole or tile by tile as
    ``config.prediction`` says (tiles in a scratch folder under ``workdir``)."""
    blocks = [
        (block.point_indices, block.table.point_values(), block.labels)
        for block in iter_scan_features(
            scan.iter_points(chunk_size=config.prediction.chunk_size),
            config=config.features,
            select=select,
            max_points_in_memory=config.prediction.max_points_in_memory,
            tile_size_m=config.prediction.tile_size_m,
            workdir=workdir,
        )
    ]
    return merge_scan_rows(blocks)


def merge_scan_rows(
    blocks: Sequence[tuple[NDArray[np.int64], NDArray[np.float32], NDArray[np.uint8] | None]],
) -> ScanRows:
    """One scan's row blocks (tiles in any order) as one set in ascending point order."""
    if not blocks:
        return np.empty(0, np.int64), np.empty((0, 0), np.float32), np.empty(0, np.uint8)
    indices = np.concatenate([block[0] for block in blocks])
    order = np.argsort(indices, kind="stable")
    rows = np.concatenate([block[1] for block in blocks])[order]
    labels = []
    for block in blocks:
        if block[2] is None:  # the scan is read with its labels: never None here
            raise RuntimeError("feature rows without labels")
        labels.append(block[2])
    return indices[order], rows, np.concatenate(labels)[order]


def _map_in_threads(function: Callable[[Any], Any], items: Sequence[Any]) -> Iterator[Any]:
    """Label passes over the scans, one scan per thread, in order."""
    return map_in_threads(function, items, name="s3d-train-labels")


def _scan_rows(
    item: tuple[LabelledScan, NDArray[np.int64]], *, config: CovarianceConfig
) -> ScanRows:
    scan, select = item
    return scan_training_rows(scan, select, config=config) if select.size else _no_rows(select)


def _no_rows(select: NDArray[np.int64]) -> ScanRows:
    return select, np.empty((0, 0), np.float32), np.empty(0, np.uint8)


def _classes_to_draw(
    counts: NDArray[np.int64], scans: Sequence[LabelledScan], config: CovarianceConfig
) -> list[int]:
    """The label values to sample: ``[sampling] classes`` or every one present."""
    present = [v for v in range(1, N_CLASSES + 1) if counts[:, v].sum() > 0]
    classes = list(config.sampling.classes) or present
    missing = [v for v in classes if counts[:, v].sum() == 0]
    if missing:
        names = ", ".join(f"{v} ({class_by_value(v).name})" for v in missing)
        raise TrainingDataError(
            f"class(es) {names} have no labelled point in the training scans "
            f"{[s.name for s in scans]}: remove them from [sampling] classes or add scans"
        )
    if len(classes) < 2:
        raise TrainingDataError(
            f"training needs at least 2 labelled classes, found {classes or 'none'} "
            f"in {[s.name for s in scans]}"
        )
    return classes


def _drawn_point_indices(
    item: tuple[LabelledScan, dict[int, NDArray[np.int64]]],
) -> NDArray[np.int64]:
    scan, ordinals = item
    return _ordinals_to_indices(scan, ordinals)


def fit_model(
    training: TrainingSet,
    *,
    config: CovarianceConfig,
    n_jobs: int | None = -1,
    grid_search: GridSearchResult | None = None,
) -> CovarianceModel:
    """Fit the forest of ``config.forest`` on a training set (``grid_search``: the search
    that chose it, recorded in the model)."""
    started = time.perf_counter()
    forest = config.forest
    classifier = CovarianceClassifier(
        n_estimators=forest.n_estimators,
        max_depth=forest.max_depth,
        min_samples_leaf=forest.min_samples_leaf,
        max_features=forest.max_features,
        n_jobs=n_jobs,
        random_state=config.sampling.seed,
    ).fit(training.features, training.labels)
    return CovarianceModel(
        classifier=classifier,
        config=config,
        feature_names=training.feature_names,
        training_scans=training.scan_names,
        n_training_points=training.counts(),
        seed=config.sampling.seed,
        package_version=__version__,
        training_time_s=training.feature_time_s + time.perf_counter() - started,
        grid_search=grid_search,
    )


def train_covariance_model(
    scans: Sequence[LabelledScan],
    *,
    config: CovarianceConfig,
    progress: Progress | None = None,
    map_scans: ItemMapper | None = None,
    rows_of_scan: RowsOfScan | None = None,
) -> CovarianceModel:
    """Sample, compute features and fit: the whole training run.

    ``map_scans`` and ``rows_of_scan`` read the scans and describe the sampled points
    elsewhere (see :func:`build_training_set`); the fit and any grid search run here.

    With ``config.grid_search.select_forest`` the forest's parameters are chosen first by
    :func:`run_grid_search` on the same sample (folds grouped by scan) and the model
    is fitted with the best ones, which replace ``config.forest`` in the model's
    configuration; the search's scores are kept in ``model.grid_search``.
    """
    training = build_training_set(
        scans,
        config=config,
        progress=progress,
        map_scans=map_scans,
        rows_of_scan=rows_of_scan,
    )
    if not config.grid_search.select_forest:
        return fit_model(training, config=config)
    started = time.perf_counter()
    result = run_grid_search(training, config=config)
    logger.info("grid search: best %s (%.4f)", result.best_params, result.best_score)
    chosen = dataclasses.replace(
        config, forest=dataclasses.replace(config.forest, **result.best_params)
    )
    model = fit_model(training, config=chosen, grid_search=result)
    return dataclasses.replace(
        model, training_time_s=model.training_time_s + time.perf_counter() - started
    )


def run_grid_search(
    training: TrainingSet, *, config: CovarianceConfig, n_jobs: int | None = -1
) -> GridSearchResult:
    """Cross-validate the grid of ``config.grid_search`` with folds grouped by scan."""
    model_selection: Any = require("sklearn.model_selection", "ml")
    grid = config.grid_search
    n_scans = len(np.unique(training.groups))
    if n_scans < 2:
        raise TrainingDataError(
            f"cross-validation grouped by scan needs at least 2 scans, found {n_scans}"
        )
    n_splits = min(grid.n_splits, n_scans)
    search = model_selection.GridSearchCV(
        CovarianceClassifier(n_jobs=n_jobs, random_state=config.sampling.seed),
        grid.param_grid,
        scoring=grid.scoring,
        cv=model_selection.GroupKFold(n_splits=n_splits),
        refit=False,
        error_score="raise",
    )
    search.fit(training.features, training.labels, groups=training.groups)
    results = search.cv_results_
    return GridSearchResult(
        params=tuple(results["params"]),
        mean_scores=np.asarray(results["mean_test_score"], np.float64),
        std_scores=np.asarray(results["std_test_score"], np.float64),
        fit_time_s=np.asarray(results["mean_fit_time"], np.float64),
        best_params=dict(search.best_params_),
        best_score=float(search.best_score_),
        scoring=grid.scoring,
        n_splits=n_splits,
    )


def _ordinals_to_indices(
    scan: LabelledScan, ordinals: dict[int, NDArray[np.int64]]
) -> NDArray[np.int64]:
    """Point indices of the drawn ordinals (k-th point of class c), streaming the labels."""
    seen = {value: 0 for value in ordinals}
    found: list[NDArray[np.int64]] = []
    offset = 0
    for chunk in scan.iter_labels():
        for value, wanted in ordinals.items():
            positions = np.flatnonzero(chunk == value)
            lo, hi = np.searchsorted(wanted, [seen[value], seen[value] + positions.size])
            found.append(positions[wanted[lo:hi] - seen[value]] + offset)
            seen[value] += positions.size
        offset += chunk.size
    return np.sort(np.concatenate(found)) if found else np.empty(0, np.int64)
