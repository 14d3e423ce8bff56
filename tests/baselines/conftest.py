"""Fixtures of the baseline tests: two generated scenes on disk and a small configuration."""

from __future__ import annotations

from pathlib import Path

import pytest

from semantic3d.baselines.covariance.config import (
    CovarianceConfig,
    ForestConfig,
    PredictionConfig,
    SamplingConfig,
)
from semantic3d.core import PointCloud
from semantic3d.features import FeatureConfig
from semantic3d.io.ascii import write_ascii_points
from tests.baselines.scene import make_street_scene

SMALL_CONFIG = CovarianceConfig(
    features=FeatureConfig(base_voxel_size_m=0.1, n_levels=6, k_neighbours=10),
    forest=ForestConfig(n_estimators=20, max_depth=15),
    sampling=SamplingConfig(points_per_class=800, seed=0),
    prediction=PredictionConfig(tile_size_m=6.4, chunk_size=20_000),
)


def write_scan(folder: Path, name: str, cloud: PointCloud, *, labels: bool = True) -> Path:
    """Write ``cloud`` as ``folder/name.txt`` (+ ``.labels``); returns the points path."""
    folder.mkdir(parents=True, exist_ok=True)
    points = folder / f"{name}.txt"
    write_ascii_points(points, [cloud], labels_path=folder / f"{name}.labels" if labels else None)
    return points


@pytest.fixture(scope="session")
def simulated_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Scans from the terrestrial scanner simulator: ``street1``, ``village1`` (training)
    and ``street2`` (another layout, held out), ~60 k points each."""
    from semantic3d.datasets.simulator import simulate

    folder = tmp_path_factory.mktemp("simulated")
    for scene, seed in (("street", 1), ("village", 1), ("street", 2)):
        result = simulate(scene, out=folder / f"{scene}{seed}", n_points=60_000, seed=seed)
        scan = result.scans[0]
        scan.points_path.rename(folder / f"{scene}{seed}.txt")
        scan.labels_path.rename(folder / f"{scene}{seed}.labels")
    return folder


@pytest.fixture(scope="session")
def scene_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``train_a``, ``train_b`` and ``test`` scenes (different layouts) as ASCII + labels."""
    folder = tmp_path_factory.mktemp("scenes")
    for name, seed in (("train_a", 10), ("train_b", 11), ("test", 12)):
        write_scan(folder, name, make_street_scene(seed))
    return folder
