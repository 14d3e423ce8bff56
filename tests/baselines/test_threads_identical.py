"""The covariance baseline trains the same model, labels a tiled scan with the same bytes
and a submission evaluates to the same numbers on any number of threads (tiles, scans and
kernels split differently)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from semantic3d.baselines.common.submission import ScanToLabel
from semantic3d.baselines.covariance.config import PredictionConfig
from semantic3d.baselines.covariance.predict import predict_scans
from semantic3d.baselines.covariance.training import (
    build_training_set,
    find_labelled_scans,
    fit_model,
)
from semantic3d.core.threads import thread_limit
from semantic3d.evaluation import custom_challenge, evaluate_submission
from tests.baselines.conftest import SMALL_CONFIG

CONFIG = dataclasses.replace(
    SMALL_CONFIG,
    prediction=PredictionConfig(tile_size_m=6.4, chunk_size=20_000, max_points_in_memory=0),
)


@pytest.mark.slow
def test_train_predict_and_evaluate_give_the_same_results_on_1_and_4_threads(
    scene_dir: Path, tmp_path: Path
) -> None:
    scans = [scan for scan in find_labelled_scans(scene_dir) if scan.name != "test"]
    targets = [
        ScanToLabel(name, scene_dir / f"{name}.txt", f"{name}.labels")
        for name in ("test", "train_a", "train_b")
    ]
    runs = []
    for n_threads in (1, 4):
        with thread_limit(n_threads):
            training = build_training_set(scans, config=CONFIG)
            model = fit_model(training, config=CONFIG)
            out = tmp_path / str(n_threads)
            predict_scans(model, targets, out, parallel_scans=2)
            result = evaluate_submission(out, challenge=custom_challenge(scene_dir))
        labels = [(out / target.output_name).read_bytes() for target in targets]
        runs.append((training, model, labels, result))
    (training_1, model_1, labels_1, result_1), (training_4, model_4, labels_4, result_4) = runs
    assert np.array_equal(training_1.features, training_4.features)
    assert np.array_equal(
        model_1.classifier.predict_proba(training_1.features),
        model_4.classifier.predict_proba(training_1.features),
    )
    assert labels_1 == labels_4
    assert np.array_equal(result_1.confusion, result_4.confusion)
    assert [scan.name for scan in result_1.per_scan] == [scan.name for scan in result_4.per_scan]
