"""Accuracy on real street scans (CMU Oakland, Munoz et al. CVPR 2009); skips without the samples."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from semantic3d.baselines.covariance.config import (
    ContextConfig,
    CovarianceConfig,
    ForestConfig,
    SamplingConfig,
)
from semantic3d.baselines.covariance.predict import predict_scan
from semantic3d.baselines.covariance.training import (
    build_training_set,
    find_labelled_scans,
    fit_model,
)
from semantic3d.features import FeatureConfig
from semantic3d.io.labels import read_labels
from semantic3d.metrics import ConfusionMatrix

CONFIG = CovarianceConfig(
    forest=ForestConfig(n_estimators=20, max_depth=20),
    sampling=SamplingConfig(points_per_class=3000),
    context=ContextConfig(potts_weight=0.0),  # the features alone (the graph cut helps both)
)


def test_multi_scale_beats_a_single_scale_on_oakland(shared_data: Path, tmp_path: Path) -> None:
    folder = shared_data / "oakland"
    train = find_labelled_scans(folder, names=["oakland_part2_ac", "oakland_part2_ad"])
    held_out = folder / "oakland_part2_ak"
    scores = {}
    for name, features in (
        ("multi", CONFIG.features),
        ("single", FeatureConfig(base_voxel_size_m=0.1, n_levels=1)),
    ):
        config = dataclasses.replace(CONFIG, features=features)
        model = fit_model(build_training_set(train, config=config), config=config)
        run = predict_scan(
            model, held_out.with_suffix(".txt"), out_path=tmp_path / f"{name}.labels"
        )
        matrix = ConfusionMatrix()
        matrix.update(read_labels(held_out.with_suffix(".labels")), read_labels(run.labels_path))
        scores[name] = matrix.compute_scores()
    assert scores["multi"].mean_iou > 0.4
    assert scores["multi"].overall_accuracy > 0.9
    assert scores["multi"].mean_iou > scores["single"].mean_iou + 0.1
