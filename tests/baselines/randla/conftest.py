"""Fixtures of the RandLA-Net baseline tests: tiny scenes, a tiny network, one trained model."""

from __future__ import annotations

import importlib.util
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from semantic3d.core import PointCloud
from tests.baselines.conftest import write_scan

if importlib.util.find_spec("torch") is None:
    collect_ignore_glob = ["test_*.py"]  # the [randla] extra is not installed

TINY_TOML = """
[blocks]
voxel_size_m = 0.1
tile_size_m = 4.0
halo_m = 1.0
max_points = 1024

[network]
k_neighbours = 8
feature_channels = 8
channels = [8, 16]
ratios = [4, 4]
dropout = 0.1

[training]
batch_size = 2
n_batches = 24
round_batches = 4
learning_rate = 0.02
decay_every = 8
checkpoint_every = 8
tile_size_m = 4.0
"""
"""Two narrow layers over 10 cm voxels in 4 m tiles: the paper's shape, ~1000x cheaper."""


def tiny_config(**tables: dict[str, Any]) -> Any:
    """The tiny configuration, with ``tables`` laid over it."""
    import tomllib

    from semantic3d.baselines.randla.config import config_from_dict

    data = tomllib.loads(TINY_TOML)
    for table, values in tables.items():
        data[table] = {**data.get(table, {}), **values}
    return config_from_dict(data)


def make_scene(
    seed: int, *, offset: tuple[float, float, float] = (500.0, 300.0, 20.0), rgb: bool = False
) -> PointCloud:
    """~2,400 labelled points on 12 m x 12 m: ground (1), a building (5), a tree crown (3),
    a car (8); colours per class when ``rgb``."""
    rng = np.random.default_rng(seed)
    ground = np.column_stack([rng.uniform(0, 12, 1200), rng.uniform(0, 12, 1200), np.zeros(1200)])
    side = rng.uniform(0, 1, (500, 3)) * [4.0, 0.0, 5.0] + [rng.uniform(1, 3), 2.0, 0.0]
    roof = rng.uniform(0, 1, (200, 3)) * [4.0, 3.0, 0.0] + [2.0, 2.0, 5.0]
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
    colour = np.zeros((2400, 3), np.uint8)
    if rgb:
        colour = (rng.integers(0, 40, (2400, 3)) + labels[:, None] * 25).astype(np.uint8)
    order = rng.permutation(len(xyz))
    return PointCloud.from_arrays(
        np.round(xyz[order] + np.asarray(offset), 3), rgb=colour[order], labels=labels[order]
    )


@pytest.fixture(scope="session")
def randla_scans(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``train`` and ``test`` tiny scenes (different layouts) as ASCII + labels."""
    folder = tmp_path_factory.mktemp("randla_scans")
    write_scan(folder, "train", make_scene(1))
    write_scan(folder, "test", make_scene(2))
    return folder


@dataclass(frozen=True)
class TrainingRun:
    """A finished tiny run: its model, progress reports and a checkpoint it wrote."""

    model: Any
    progress: list[Any]
    checkpoint_8: Path


@pytest.fixture(scope="session")
def training_run(randla_scans: Path, tmp_path_factory: pytest.TempPathFactory) -> TrainingRun:
    """A tiny model trained on ``train`` (24 batches, a checkpoint every 8)."""
    from semantic3d.baselines.common.scans import find_labelled_scans
    from semantic3d.baselines.randla.training import train_randla_model

    folder = tmp_path_factory.mktemp("randla_run")
    checkpoint = folder / "run.checkpoint"
    seen: list[Any] = []

    def progress(state: Any) -> None:
        seen.append(state)
        if state.batch == 9 and state.stage == "train":  # the one of batch 8 is on disk
            shutil.copy(checkpoint, folder / "after8.checkpoint")

    model = train_randla_model(
        find_labelled_scans(randla_scans, names=["train"]),
        config=tiny_config(),
        checkpoint=checkpoint,
        progress=progress,
    )
    return TrainingRun(model, seen, folder / "after8.checkpoint")


@pytest.fixture(scope="session")
def trained(training_run: TrainingRun) -> Any:
    """The model of :func:`training_run`."""
    return training_run.model
