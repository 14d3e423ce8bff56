"""Fixtures of the scale-out tests: one local cluster of worker processes, small scans, a model.

Worker processes are slow to start on a loaded machine, so one ``LocalCluster`` of two
processes serves every test of the package that needs one.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from pathlib import Path

import pytest

from semantic3d.baselines.covariance.config import ContextConfig, ForestConfig, PredictionConfig
from semantic3d.baselines.covariance.model import CovarianceModel
from semantic3d.scale.cluster import ClusterSpec, DaskCluster, connect
from tests.baselines.conftest import SMALL_CONFIG, write_scan
from tests.baselines.scene import make_street_scene

pytest.importorskip("distributed")

TINY_CONFIG = dataclasses.replace(
    SMALL_CONFIG,
    forest=ForestConfig(n_estimators=4, max_depth=10),
    prediction=PredictionConfig(tile_size_m=4.8, chunk_size=4_000, max_points_in_memory=10**7),
    context=ContextConfig(max_graph_nodes=200),
)
"""Small forest, small tiles (a scan of ~14 m makes about ten), the denser tiles' graphs cut
in squares."""


@pytest.fixture(scope="session")
def cluster() -> Iterator[DaskCluster]:
    """Two worker processes on this machine, one thread each."""
    with connect(ClusterSpec(n_workers=2, threads_per_worker=1)) as opened:
        yield opened


@pytest.fixture(scope="session")
def scan_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``train``, ``test`` and ``other`` street scenes (14 m square, ~6 k points) as ASCII + labels."""
    folder = tmp_path_factory.mktemp("scale-scans")
    for name, seed in (("train", 10), ("test", 12), ("other", 13)):
        write_scan(folder, name, make_street_scene(seed, size_m=14.0, spacing_m=0.2)[::4])
    return folder


@pytest.fixture(scope="session")
def model(scan_dir: Path) -> CovarianceModel:
    """A small covariance model trained on ``train``."""
    from semantic3d.baselines.covariance.training import (
        build_training_set,
        find_labelled_scans,
        fit_model,
    )

    scans = find_labelled_scans(scan_dir, names=["train"])
    return fit_model(build_training_set(scans, config=TINY_CONFIG), config=TINY_CONFIG)
