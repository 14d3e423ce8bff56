"""Training: class-balanced sampling, bad training data, and accuracy on a held-out scene."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from numpy.typing import NDArray

from semantic3d.baselines.covariance.config import SamplingConfig
from semantic3d.baselines.covariance.predict import predict_scan
from semantic3d.baselines.covariance.training import (
    LabelledScan,
    ScanRows,
    TrainingDataError,
    build_training_set,
    find_labelled_scans,
    fit_model,
    run_grid_search,
    sample_training_points,
    scan_training_rows,
)
from semantic3d.io.labels import read_labels
from semantic3d.metrics import ConfusionMatrix
from tests.baselines.conftest import SMALL_CONFIG, write_scan
from tests.baselines.scene import make_street_scene


def test_sampling_draws_a_fixed_number_per_class_over_all_scans() -> None:
    counts = np.zeros((3, 9), np.int64)
    counts[:, 1] = [1000, 0, 500]
    counts[:, 4] = [10, 20, 5]
    drawn = sample_training_points(counts, points_per_class=300, classes=[1, 4], seed=1)
    assert sum(d[1].size for d in drawn) == 300
    assert sum(d[4].size for d in drawn) == 35  # fewer than asked: all of them
    for scan, d in enumerate(drawn):
        assert np.all(np.diff(d[1]) > 0) and (d[1].size == 0 or d[1].max() < counts[scan, 1])
    assert drawn[1][1].size == 0
    again = sample_training_points(counts, points_per_class=300, classes=[1, 4], seed=1)
    assert all(np.array_equal(a[1], b[1]) for a, b in zip(drawn, again, strict=True))


def test_training_set_is_class_balanced_and_grouped_by_scan(scene_dir: Path) -> None:
    scans = find_labelled_scans(scene_dir, names=["train_a", "train_b"])
    training = build_training_set(scans, config=SMALL_CONFIG)
    counts = training.counts()
    assert set(counts) == {1, 2, 3, 4, 5, 6, 8}
    assert all(n == 800 for n in counts.values())
    assert set(np.unique(training.groups)) == {0, 1}
    assert training.features.shape == (training.labels.size, SMALL_CONFIG.features.n_features)
    assert training.feature_names == SMALL_CONFIG.features.feature_names


def test_training_set_does_not_depend_on_how_the_scans_are_cut(scene_dir: Path) -> None:
    """Rows in ascending point order whether a scan is described whole or tile by tile."""
    scans = find_labelled_scans(scene_dir, names=["train_a", "train_b"])
    whole = build_training_set(scans, config=SMALL_CONFIG)
    tiled_config = dataclasses.replace(
        SMALL_CONFIG,
        prediction=dataclasses.replace(
            SMALL_CONFIG.prediction, max_points_in_memory=0, tile_size_m=4.8
        ),
    )
    tiled = build_training_set(scans, config=tiled_config)
    np.testing.assert_array_equal(tiled.features, whole.features)
    np.testing.assert_array_equal(tiled.labels, whole.labels)
    np.testing.assert_array_equal(tiled.groups, whole.groups)


@pytest.mark.parametrize(("budget", "at_once"), [(1, 1), (2, 2)])
def test_scans_are_described_at_once_on_shares_that_fill_the_thread_budget(
    scene_dir: Path, monkeypatch: pytest.MonkeyPatch, budget: int, at_once: int
) -> None:
    """Scans go ``budget // 4`` at a time, at least 2, each with its share of numba's
    threads: on a 2-thread budget two scans on one thread each (before, one scan ran
    alone on one thread and the other thread idled)."""
    import threading

    import numba

    from semantic3d.baselines.covariance import training as training_module
    from semantic3d.core.threads import thread_limit

    together = threading.Barrier(at_once, timeout=30)  # breaks unless they run at once
    seen: list[int] = []
    describe = training_module.scan_training_rows

    def counting(scan: LabelledScan, select: NDArray[np.int64], **kwargs: object) -> ScanRows:
        seen.append(numba.get_num_threads())
        together.wait()
        return describe(scan, select, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(training_module, "scan_training_rows", counting)
    scans = find_labelled_scans(scene_dir, names=["train_a", "train_b"])
    with thread_limit(budget):
        build_training_set(scans, config=SMALL_CONFIG)
    assert seen == [budget // at_once] * 2


def test_a_rows_of_scan_hook_that_loses_points_is_caught(scene_dir: Path) -> None:
    scans = find_labelled_scans(scene_dir, names=["train_a"])

    def lossy(scan: LabelledScan, select: NDArray[np.int64]) -> ScanRows:
        indices, rows, labels = scan_training_rows(scan, select, config=SMALL_CONFIG)
        return indices[1:], rows[1:], labels[1:]

    with pytest.raises(RuntimeError, match="train_a: rows for"):
        build_training_set(scans, config=SMALL_CONFIG, rows_of_scan=lossy)


def test_model_beats_a_trivial_classifier_on_a_held_out_simulated_scan(
    simulated_dir: Path, tmp_path: Path
) -> None:
    """Train on two simulated terrestrial scans, label a third scene layout."""
    scans = find_labelled_scans(simulated_dir, names=["street1", "village1"])
    model = fit_model(build_training_set(scans, config=SMALL_CONFIG), config=SMALL_CONFIG)
    run = predict_scan(model, simulated_dir / "street2.txt", out_path=tmp_path / "p.labels")
    truth = read_labels(simulated_dir / "street2.labels")
    scores = _scores(truth, read_labels(run.labels_path))
    trivial = _scores(truth, np.full_like(truth, np.bincount(truth).argmax()))
    # measured: mIoU 0.59 vs 0.06, OA 0.94 vs 0.50
    assert scores.mean_iou > trivial.mean_iou + 0.35, (scores.mean_iou, trivial.mean_iou)
    assert scores.overall_accuracy > trivial.overall_accuracy + 0.3


def test_model_separates_the_generated_street_scene(scene_dir: Path, tmp_path: Path) -> None:
    """The small generated scene (shapes only): near-perfect on a held-out layout."""
    scans = find_labelled_scans(scene_dir, names=["train_a", "train_b"])
    model = fit_model(build_training_set(scans, config=SMALL_CONFIG), config=SMALL_CONFIG)
    run = predict_scan(model, scene_dir / "test.txt", out_path=tmp_path / "test.labels")
    truth = read_labels(scene_dir / "test.labels")
    scores = _scores(truth, read_labels(run.labels_path))
    trivial = _scores(truth, np.full_like(truth, np.bincount(truth).argmax()))
    # measured: mIoU 0.87 vs 0.06, OA 0.96 vs 0.42
    assert scores.mean_iou > max(0.6, trivial.mean_iou + 0.5), (scores.mean_iou, trivial.mean_iou)
    assert scores.overall_accuracy > trivial.overall_accuracy + 0.3


def test_a_scan_without_labels_cannot_train(tmp_path: Path) -> None:
    write_scan(tmp_path, "bare", make_street_scene(1, size_m=20), labels=False)
    with pytest.raises(
        TrainingDataError, match=r"bare.txt: training needs labels: expected bare.labels"
    ):
        find_labelled_scans(tmp_path)


def test_a_missing_scan_name_is_reported(scene_dir: Path) -> None:
    with pytest.raises(TrainingDataError, match=r"scan\(s\) \['nope'\] not found"):
        find_labelled_scans(scene_dir, names=["nope"])


def test_a_requested_class_missing_from_the_training_data_is_an_error(scene_dir: Path) -> None:
    config = dataclasses.replace(
        SMALL_CONFIG, sampling=SamplingConfig(points_per_class=10, classes=(1, 7))
    )
    scans = find_labelled_scans(scene_dir, names=["train_a"])
    with pytest.raises(TrainingDataError, match=r"7 \(scanning artefacts\) have no labelled point"):
        build_training_set(scans, config=config)


def test_a_single_class_cannot_train(tmp_path: Path) -> None:
    cloud = make_street_scene(2, size_m=20)
    write_scan(tmp_path, "flat", cloud.with_labels(np.ones(cloud.n_points, np.uint8)))
    with pytest.raises(TrainingDataError, match="at least 2 labelled classes"):
        build_training_set(find_labelled_scans(tmp_path), config=SMALL_CONFIG)


def test_grid_search_folds_are_grouped_by_scan(scene_dir: Path) -> None:
    config = dataclasses.replace(
        SMALL_CONFIG,
        sampling=SamplingConfig(points_per_class=150),
        grid_search=dataclasses.replace(
            SMALL_CONFIG.grid_search, n_estimators=(5,), max_depth=(4, None), min_samples_leaf=(1,)
        ),
    )
    scans = find_labelled_scans(scene_dir, names=["train_a", "train_b", "test"])
    result = run_grid_search(build_training_set(scans, config=config), config=config)
    assert result.n_splits == 3  # min(5, number of scans)
    assert len(result.params) == 2 and np.isfinite(result.mean_scores).all()
    assert result.best_params["max_depth"] is None  # full trees beat depth-4 stumps
    assert result.best_score == pytest.approx(result.mean_scores.max())


def _scores(truth: np.ndarray, predicted: np.ndarray):  # type: ignore[no-untyped-def]
    matrix = ConfusionMatrix()
    matrix.update(truth, predicted)
    return matrix.compute_scores()
