"""CNN prediction on a cluster of worker processes equals the single-process path's, byte for byte."""

from __future__ import annotations

import filecmp
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from semantic3d.baselines.common.submission import ScanToLabel
from semantic3d.scale.cluster import DaskCluster
from semantic3d.scale.predict_cnn import ClusterCnnPredictor

torch = pytest.importorskip("torch")


def _model(centring: str) -> Any:
    from semantic3d.baselines.cnn.config import (
        CnnConfig,
        CubeConfig,
        NetworkConfig,
        PredictionConfig,
    )
    from semantic3d.baselines.cnn.model import CnnModel
    from semantic3d.baselines.cnn.network import build_network

    config = CnnConfig(
        cubes=CubeConfig(voxel_sizes_m=(0.25, 0.5, 1.0), cube_voxels=8, centring=centring),
        network=NetworkConfig(channels=(4, 8, 8), hidden_units=32, dropout=0.1),
        prediction=PredictionConfig(tile_size_m=4.0, batch_size=512, chunk_size=1000),
    )
    torch.manual_seed(3)
    network = build_network(config.cubes, config.network)
    with torch.no_grad():  # untrained, without biases: the labels follow the cubes
        for name, parameter in network.named_parameters():
            if name.endswith("bias"):
                parameter.zero_()
    return CnnModel(
        network,
        config=config,
        label_values=(1, 2, 3, 4, 5, 6, 8),
        training_scans=(),
        seed=3,
        n_batches_trained=0,
        training_time_s=0.0,
        package_version="test",
    )


@pytest.mark.parametrize("centring", ["point", "corner"])
def test_cnn_predict_many_scans_identical(
    cluster: DaskCluster, scan_dir: Path, tmp_path: Path, centring: str
) -> None:
    from semantic3d.baselines.common.prediction import predict_scans

    model = _model(centring)
    scans = [
        ScanToLabel(name, scan_dir / f"{name}.txt", f"{name}.labels") for name in ("test", "other")
    ]
    single = predict_scans(model, scans, tmp_path / "single")
    (tmp_path / "scratch").mkdir()
    distributed = predict_scans(
        ClusterCnnPredictor(model, cluster),
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
    assert not any((tmp_path / "scratch").rglob("cnn-*"))  # scratch files removed
