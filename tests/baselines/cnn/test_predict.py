"""Prediction: tiled labels equal whole-scan labels, through the shared loop; model files."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from semantic3d.baselines.cnn.model import CnnModel
from semantic3d.baselines.cnn.persistence import load_model, read_model_header, save_model
from semantic3d.baselines.common.modelfile import ModelFileError
from semantic3d.baselines.common.prediction import predict_scan
from semantic3d.io.formats import read_points
from semantic3d.io.labels import read_labels
from semantic3d.metrics import ConfusionMatrix


def _with_prediction(model: Any, **changes: Any) -> CnnModel:
    config = dataclasses.replace(
        model.config, prediction=dataclasses.replace(model.config.prediction, **changes)
    )
    return CnnModel(
        model.network,
        config=config,
        label_values=model.label_values,
        training_scans=model.training_scans,
        seed=model.seed,
        n_batches_trained=model.n_batches_trained,
        training_time_s=model.training_time_s,
        package_version=model.package_version,
    )


def test_tiled_labels_equal_whole_scan_labels_in_input_order(
    trained: Any, cnn_scans: Path, tmp_path: Path
) -> None:
    cloud = read_points(cnn_scans / "test.txt")
    whole = trained.label_cloud(cloud)  # one occupancy for the whole scan, no tiles
    run = predict_scan(trained, cnn_scans / "test.txt", out_path=tmp_path / "test.labels")
    assert run.tiled  # 4 m tiles over a 12 m scene
    np.testing.assert_array_equal(read_labels(tmp_path / "test.labels"), whole)
    record = json.loads((tmp_path / "test.labels.json").read_text())
    assert record["n_points"] == cloud.n_points and record["training_scans"] == ["train"]
    matrix = ConfusionMatrix()
    matrix.update(read_labels(cnn_scans / "test.labels"), whole)
    assert matrix.compute_scores().iou[0] > 0.5  # ground, on a held-out layout


def test_classifying_identical_cubes_once_gives_the_per_point_labels(
    trained: Any, cnn_scans: Path
) -> None:
    cloud = read_points(cnn_scans / "test.txt")
    cloud = cloud[:600]
    doubled = type(cloud).concatenate([cloud, cloud])  # every cube twice
    per_point = _with_prediction(trained, deduplicate=False).label_cloud(doubled)
    np.testing.assert_array_equal(trained.label_cloud(doubled), per_point)


def test_model_file_round_trip_and_version_check(trained: Any, tmp_path: Path) -> None:
    path = save_model(trained, tmp_path / "model.cnn")
    header = read_model_header(path)
    assert header["format_version"] == 1 and header["label_values"] == [1, 3, 5, 8]
    loaded = load_model(path)
    for key, value in trained.network.state_dict().items():
        assert torch.equal(loaded.network.state_dict()[key], value)
    assert loaded.config == trained.config and loaded.training_scans == ("train",)
    raw = path.read_bytes()
    newer = raw.replace(b'"format_version": 1', b'"format_version": 2', 1)
    (tmp_path / "newer.cnn").write_bytes(newer)
    with pytest.raises(ModelFileError, match="expected format semantic3d-cnn-model v1, found"):
        load_model(tmp_path / "newer.cnn")
    (tmp_path / "other.cnn").write_bytes(b"S3DCOV1 {}\n")
    with pytest.raises(ModelFileError, match="not a semantic3d cnn model"):
        load_model(tmp_path / "other.cnn")


@pytest.mark.gpu
def test_cuda_prediction_agrees_with_the_cpu(trained: Any, cnn_scans: Path) -> None:
    if not torch.cuda.is_available():
        pytest.skip("no CUDA device")
    cloud = read_points(cnn_scans / "test.txt")
    on_cpu = trained.label_cloud(cloud)
    gpu_model = _with_prediction(trained).to("cuda")
    on_gpu = gpu_model.label_cloud(cloud)  # cubes filled on the GPU, bf16 autocast
    assert np.mean(on_gpu == on_cpu) > 0.99


@pytest.mark.gpu
def test_cuda_cubes_equal_the_compiled_ones() -> None:
    if not torch.cuda.is_available():
        pytest.skip("no CUDA device")
    from semantic3d.baselines.cnn.cubes import build_occupancy, compute_corner_cells, fill_cubes
    from semantic3d.baselines.cnn.cubes_torch import DeviceOccupancy

    points = np.random.default_rng(0).uniform(0, 4, (5000, 3))
    sizes = (0.025, 0.05, 0.1, 0.2, 0.4)
    occupancy = build_occupancy(points, origin=np.zeros(3), voxel_sizes_m=sizes)
    corners = compute_corner_cells(
        points[::10], origin=np.zeros(3), voxel_sizes_m=sizes, cube_voxels=16
    )
    on_gpu = DeviceOccupancy(occupancy, device="cuda", cube_voxels=16).fill(corners)
    np.testing.assert_array_equal(
        on_gpu.cpu().numpy(), fill_cubes(occupancy, corners, cube_voxels=16)
    )
