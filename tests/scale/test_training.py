"""Training on a cluster: the same training set, array for array, and the same model."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from semantic3d.baselines.covariance.config import SamplingConfig
from semantic3d.baselines.covariance.training import (
    TrainingDataError,
    build_training_set,
    find_labelled_scans,
    fit_model,
    train_covariance_model,
)
from semantic3d.scale.cluster import DaskCluster
from semantic3d.scale.tiled_scans import open_tiled_scan
from semantic3d.scale.training import (
    build_training_set_on_cluster,
    tile_training_rows,
    train_covariance_model_on_cluster,
)
from tests.scale.conftest import TINY_CONFIG

TILED_CONFIG = dataclasses.replace(
    TINY_CONFIG,
    prediction=dataclasses.replace(TINY_CONFIG.prediction, max_points_in_memory=0),
)
"""The single-process path tiles the scans too (the default config describes them whole)."""


@pytest.mark.parametrize("config", [TINY_CONFIG, TILED_CONFIG], ids=["whole", "tiled"])
def test_training_set_identical(
    cluster: DaskCluster, scan_dir: Path, tmp_path: Path, config: object
) -> None:
    assert isinstance(config, type(TINY_CONFIG))
    scans = find_labelled_scans(scan_dir, names=["train", "other"])
    single = build_training_set(scans, config=config)
    tiles_seen: list[tuple[int, int]] = []
    distributed = build_training_set_on_cluster(
        scans,
        config=config,
        cluster=cluster,
        workdir=tmp_path / "scratch",
        tile_progress=lambda done, total: tiles_seen.append((done, total)),
    )
    np.testing.assert_array_equal(distributed.features, single.features)
    np.testing.assert_array_equal(distributed.labels, single.labels)
    np.testing.assert_array_equal(distributed.groups, single.groups)
    assert distributed.scan_names == single.scan_names == ("train", "other")
    assert set(np.unique(single.groups)) == {0, 1} and len(set(single.counts().values())) > 0
    assert tiles_seen[-1][0] == tiles_seen[-1][1] > 1  # the last scan went tile by tile
    assert list((tmp_path / "scratch").iterdir()) == []  # scratch folders removed


def test_model_identical(cluster: DaskCluster, scan_dir: Path) -> None:
    scans = find_labelled_scans(scan_dir, names=["train", "other"])
    single = train_covariance_model(scans, config=TINY_CONFIG)
    distributed = train_covariance_model_on_cluster(scans, config=TINY_CONFIG, cluster=cluster)
    rows = build_training_set(scans, config=TINY_CONFIG).features
    assert distributed.n_training_points == single.n_training_points
    np.testing.assert_array_equal(
        distributed.classifier.predict_proba(rows), single.classifier.predict_proba(rows)
    )
    reference = fit_model(build_training_set(scans, config=TINY_CONFIG), config=TINY_CONFIG)
    np.testing.assert_array_equal(
        reference.classifier.predict_proba(rows), single.classifier.predict_proba(rows)
    )


def test_bad_training_data_is_the_same_error(cluster: DaskCluster, scan_dir: Path) -> None:
    scans = find_labelled_scans(scan_dir, names=["train"])
    config = dataclasses.replace(
        TINY_CONFIG, sampling=SamplingConfig(points_per_class=50, classes=(1, 7), seed=0)
    )
    with pytest.raises(TrainingDataError) as single:
        build_training_set(scans, config=config)
    with pytest.raises(TrainingDataError) as distributed:
        build_training_set_on_cluster(scans, config=config, cluster=cluster)
    assert str(distributed.value) == str(single.value)


def test_a_tile_without_drawn_points_gives_no_rows(scan_dir: Path, tmp_path: Path) -> None:
    import pickle

    from semantic3d.features.tiling import TiledScan

    (scan,) = find_labelled_scans(scan_dir, names=["train"])
    selection = tmp_path / "select.npy"
    np.save(selection, np.array([0], np.int64))
    with TiledScan(
        scan.iter_points(),
        config=TINY_CONFIG.features,
        tile_size_m=TINY_CONFIG.prediction.tile_size_m,
        workdir=tmp_path,
    ) as tiled:
        state = pickle.dumps(tiled)
        rows = [
            tile_training_rows(str(tiled.workdir), state, str(selection), t) for t in tiled.tiles
        ]
        assert open_tiled_scan(str(tiled.workdir), state).n_points == tiled.n_points
    found = [r for r in rows if r[0].size]
    assert len(found) == 1 and found[0][0].tolist() == [0]
    assert found[0][1].shape == (1, TINY_CONFIG.features.n_features)
    assert all(r[1].shape[0] == r[0].size == r[2].size for r in rows)
