"""Tiled prediction on a cluster of worker processes equals the single-process path's, byte
for byte (the RandLA-Net baseline through the generic ClusterTilePredictor)."""

from __future__ import annotations

import filecmp
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from semantic3d.baselines.common.submission import ScanToLabel
from semantic3d.scale.cluster import DaskCluster

torch = pytest.importorskip("torch")
pytest.importorskip("pgeof")


def _model() -> Any:
    from semantic3d.baselines.randla.config import config_from_dict
    from semantic3d.baselines.randla.model import RandlaModel
    from semantic3d.baselines.randla.network import build_network

    config = config_from_dict(
        {
            "blocks": {"voxel_size_m": 0.2, "tile_size_m": 4.0, "halo_m": 1.0, "max_points": 256},
            "network": {"k_neighbours": 6, "channels": [8, 16], "ratios": [4, 4]},
            "prediction": {"chunk_size": 1000},
        }
    )
    torch.manual_seed(3)
    network = build_network(config.inputs.n_inputs, 7, config.network)
    with torch.no_grad():  # untrained: make the logits follow the points, not the biases
        network.head[-1].weight.mul_(100.0)
    return RandlaModel(
        network,
        config=config,
        label_values=(1, 2, 3, 4, 5, 6, 8),
        training_scans=(),
        seed=3,
        n_batches_trained=0,
        training_time_s=0.0,
        package_version="test",
    )


def test_randla_predict_identical(cluster: DaskCluster, scan_dir: Path, tmp_path: Path) -> None:
    from semantic3d.baselines.common.prediction import predict_scans
    from semantic3d.scale.predict_tiles import ClusterTilePredictor

    model = _model()
    scans = [ScanToLabel(name, scan_dir / f"{name}.txt", f"{name}.labels") for name in ("test",)]
    single = predict_scans(model, scans, tmp_path / "single")
    (tmp_path / "scratch").mkdir()
    distributed = predict_scans(
        ClusterTilePredictor(model, cluster),
        scans,
        tmp_path / "cluster",
        workdir=tmp_path / "scratch",
    )
    for scan, run in zip(scans, distributed.runs, strict=True):
        written = tmp_path / "cluster" / scan.output_name
        assert filecmp.cmp(tmp_path / "single" / scan.output_name, written, shallow=False)
        labels = np.loadtxt(written, dtype=np.int64)
        assert run.tiled and len(np.unique(labels)) > 1  # several tiles, not one constant
    assert [r.n_points for r in single.runs] == [r.n_points for r in distributed.runs]
    assert not any((tmp_path / "scratch").rglob("tiled-*"))  # scratch files removed
