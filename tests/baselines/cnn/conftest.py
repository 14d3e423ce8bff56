"""Fixtures of the CNN baseline tests: tiny scenes, a tiny network, one trained model."""

from __future__ import annotations

import importlib.util
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from semantic3d.baselines.cnn.config import (
    CnnConfig,
    CubeConfig,
    NetworkConfig,
    PredictionConfig,
    TrainingConfig,
)
from semantic3d.core import PointCloud
from tests.baselines.conftest import write_scan

if importlib.util.find_spec("torch") is None:  # the [torch] extra is not installed
    collect_ignore_glob = ["test_*.py"]

TINY = CnnConfig(
    # Corner-centred: the figures these tests expect of a 30-batch run were measured so;
    # point-centred cubes (the default) have their own tests (test_cubes_exact.py).
    cubes=CubeConfig(voxel_sizes_m=(0.25, 0.5, 1.0), cube_voxels=8, centring="corner"),
    network=NetworkConfig(channels=(4, 8, 8), hidden_units=32, dropout=0.1),
    training=TrainingConfig(
        batch_size=16, n_batches=30, rotate_every=10, checkpoint_every=10, tile_size_m=8.0
    ),
    prediction=PredictionConfig(tile_size_m=4.0, batch_size=512, chunk_size=1000),
)
"""Three scales of 8^3 cubes and a narrow network: the paper's shape, ~1000x cheaper."""

TINY_TOML = """
[cubes]
voxel_sizes_m = [0.25, 0.5, 1.0]
cube_voxels = 8

[network]
channels = [4, 8, 8]
hidden_units = 32
dropout = 0.1

[training]
batch_size = 16
n_batches = 30
rotate_every = 10
checkpoint_every = 10
tile_size_m = 8.0

[prediction]
tile_size_m = 4.0
chunk_size = 1000
"""


def make_scene(
    seed: int, *, offset: tuple[float, float, float] = (500.0, 300.0, 20.0)
) -> PointCloud:
    """~2,400 labelled points: ground (1), a box building (5), a tree crown (3), a car (8)."""
    rng = np.random.default_rng(seed)
    ground = np.column_stack([rng.uniform(0, 12, 1200), rng.uniform(0, 12, 1200), np.zeros(1200)])
    side = rng.uniform(0, 1, (500, 3)) * [4.0, 0.0, 5.0] + [rng.uniform(1, 3), 2.0, 0.0]
    roof = rng.uniform(0, 1, (200, 3)) * [4.0, 3.0, 0.0] + [side[0, 0] * 0 + 2.0, 2.0, 5.0]
    direction = rng.normal(size=(350, 3))
    crown = direction / np.linalg.norm(direction, axis=1, keepdims=True) * 1.5 + [
        rng.uniform(3, 9),
        8.5,
        4.0,
    ]
    car = rng.uniform(0, 1, (150, 3)) * [4.0, 1.8, 1.4] + [rng.uniform(2, 6), 5.5, 0.1]
    parts = [(ground, 1), (side, 5), (roof, 5), (crown, 3), (car, 8)]
    xyz = np.concatenate([p for p, _ in parts]) + 0.01 * rng.normal(size=(2400, 3))
    labels = np.concatenate([np.full(len(p), v, np.uint8) for p, v in parts])
    order = rng.permutation(len(xyz))
    return PointCloud.from_arrays(
        np.round(xyz[order] + np.asarray(offset), 3), labels=labels[order]
    )


@pytest.fixture(scope="session")
def cnn_scans(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``train`` and ``test`` tiny scenes (different layouts) as ASCII + labels."""
    folder = tmp_path_factory.mktemp("cnn_scans")
    write_scan(folder, "train", make_scene(1))
    write_scan(folder, "test", make_scene(2))
    return folder


@dataclass(frozen=True)
class TrainingRun:
    """A finished tiny run: its model, progress reports and the checkpoints it wrote."""

    model: Any
    progress: list[Any]
    checkpoint_10: Path
    checkpoint_20: Path


@pytest.fixture(scope="session")
def training_run(cnn_scans: Path, tmp_path_factory: pytest.TempPathFactory) -> TrainingRun:
    """A tiny model trained on ``train`` (30 batches, a checkpoint every 10)."""
    from semantic3d.baselines.cnn.training import train_cnn_model
    from semantic3d.baselines.common.scans import find_labelled_scans

    folder = tmp_path_factory.mktemp("cnn_run")
    checkpoint = folder / "run.checkpoint"
    seen: list[Any] = []

    def progress(state: Any) -> None:
        seen.append(state)
        if state.batch == 11 and state.stage == "train":  # the one of batch 10 is on disk
            shutil.copy(checkpoint, folder / "after10.checkpoint")

    model = train_cnn_model(
        find_labelled_scans(cnn_scans, names=["train"]),
        config=TINY,
        checkpoint=checkpoint,
        progress=progress,
    )
    return TrainingRun(model, seen, folder / "after10.checkpoint", checkpoint)


@pytest.fixture(scope="session")
def trained(training_run: TrainingRun) -> Any:
    """The model of :func:`training_run`."""
    return training_run.model
