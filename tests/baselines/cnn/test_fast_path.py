"""The fast labelling path (producer thread, channels-last, compiled once, float16 with a
float32 fallback) gives the labels of the plain reference path."""

from __future__ import annotations

import copy
import dataclasses
import logging
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from semantic3d.baselines.cnn.config import CnnConfig
from semantic3d.baselines.cnn.cubes import build_occupancy, compute_cubes
from semantic3d.baselines.cnn.inference import COMPILE_AFTER_POINTS, InferenceNetwork
from semantic3d.baselines.cnn.labelling import label_tile_points
from semantic3d.baselines.cnn.model import CnnModel
from semantic3d.baselines.common.pipeline import Prefetched
from semantic3d.io.formats import read_points
from tests.baselines.cnn.conftest import TINY

POINT = dataclasses.replace(TINY, cubes=dataclasses.replace(TINY.cubes, centring="point"))
TIE = 1e-4
"""Float32 logits closer than this may order differently in another summation order."""


def _model(config: CnnConfig, network: Any, **prediction: Any) -> CnnModel:
    config = dataclasses.replace(
        config, prediction=dataclasses.replace(config.prediction, **prediction)
    )
    return CnnModel(
        network,
        config=config,
        label_values=(1, 3, 5, 8),
        training_scans=("train",),
        seed=0,
        n_batches_trained=0,
        training_time_s=0.0,
        package_version="0",
    )


def reference_logits(model: CnnModel, xyz: np.ndarray) -> np.ndarray:
    """The plain path: every point's cubes by the compiled kernel, one batch after the
    other, an eager float32 copy of the network in the default layout."""
    cubes = model.config.cubes
    network = copy.deepcopy(model.network).to(memory_format=torch.contiguous_format).eval()
    origin = model.grid_origin(xyz[0])
    occupancy = build_occupancy(
        xyz, origin=origin, voxel_sizes_m=cubes.voxel_sizes_m, centring=cubes.centring
    )
    parts = []
    with torch.inference_mode():
        for begin in range(0, len(xyz), 100):
            filled = compute_cubes(
                occupancy,
                xyz[begin : begin + 100],
                cube_voxels=cubes.cube_voxels,
                centring=cubes.centring,
            )
            parts.append(network(torch.from_numpy(filled)).numpy())
    logits = np.concatenate(parts)
    logits[:, [v - 1 for v in range(1, 9) if v not in model.label_values]] = -np.inf
    return logits


def assert_same_labels_but_ties(labels: np.ndarray, logits: np.ndarray) -> None:
    expected = logits.argmax(axis=1) + 1
    differ = np.flatnonzero(labels != expected)
    top = np.sort(logits, axis=1)
    assert np.all(top[differ, -1] - top[differ, -2] < TIE), differ


def test_fast_labels_equal_reference_labels(trained: Any, cnn_scans: Path) -> None:
    xyz = np.asarray(read_points(cnn_scans / "test.txt").xyz)
    for config in (POINT, TINY):  # point- and corner-centred cubes
        model = _model(config, trained.network, batch_size=300)
        labels = model.label_cloud(read_points(cnn_scans / "test.txt"))
        assert_same_labels_but_ties(labels, reference_logits(model, xyz))
        assert len(np.unique(labels)) > 1


def test_device_cubes_on_the_cpu_give_the_host_labels(trained: Any, cnn_scans: Path) -> None:
    """The GPU's path (cubes made by the torch kernels, per tile), run on the CPU device."""
    xyz = np.asarray(read_points(cnn_scans / "test.txt").xyz)[:900]
    for config in (POINT, TINY):
        model = _model(config, trained.network, batch_size=128)
        cubes = config.cubes
        occupancy = build_occupancy(
            xyz,
            origin=model.grid_origin(xyz[0]),
            voxel_sizes_m=cubes.voxel_sizes_m,
            centring=cubes.centring,
        )
        host = label_tile_points(model.inference, xyz, occupancy, cubes=cubes)
        device = label_tile_points(model.inference, xyz, occupancy, cubes=cubes, device_cubes=True)
        np.testing.assert_array_equal(device, host)


class CountingCompiler:
    """Stands in for ``torch.compile``: counts compilations and the shapes run."""

    def __init__(self, fail: bool = False) -> None:
        self.compiled = 0
        self.shapes: list[tuple[int, ...]] = []
        self.fail = fail

    def __call__(self, module: Any) -> Any:
        self.compiled += 1

        def run(cubes: torch.Tensor) -> torch.Tensor:
            if self.fail:
                raise RuntimeError("backend exploded")
            self.shapes.append(tuple(cubes.shape))
            return module(cubes)

        return run


def _inference(model: CnnModel, mode: str, compiler: Any) -> InferenceNetwork:
    return InferenceNetwork(
        model.network,
        device="cpu",
        precision="auto",
        compile=mode,
        batch_size=256,
        logit_mask=model._logit_mask,
        compiler=compiler,
    )


def test_compiled_once_for_one_shape_and_eager_when_it_fails(
    trained: Any, cnn_scans: Path, caplog: pytest.LogCaptureFixture
) -> None:
    model = _model(POINT, trained.network)
    xyz = np.asarray(read_points(cnn_scans / "test.txt").xyz)[:700]
    cubes = POINT.cubes
    occupancy = build_occupancy(
        xyz, origin=model.grid_origin(xyz[0]), voxel_sizes_m=cubes.voxel_sizes_m, centring="point"
    )
    eager = label_tile_points(_inference(model, "never", None), xyz, occupancy, cubes=cubes)
    compiler = CountingCompiler()
    network = _inference(model, "always", compiler)
    for _ in range(2):  # two scans, one compilation
        np.testing.assert_array_equal(
            label_tile_points(network, xyz, occupancy, cubes=cubes), eager
        )
    assert compiler.compiled == 1 and network.compiled
    assert set(compiler.shapes) == {(256, 3, 8, 8, 8)}  # 700 points: the last batch padded
    auto = _inference(model, "auto", CountingCompiler())
    label_tile_points(auto, xyz, occupancy, cubes=cubes)
    assert not auto.compiled  # 700 points do not pay for a compilation
    auto.expect(COMPILE_AFTER_POINTS["cpu"])
    label_tile_points(auto, xyz, occupancy, cubes=cubes)
    assert auto.compiled
    failing = _inference(model, "always", CountingCompiler(fail=True))
    with caplog.at_level(logging.WARNING):
        np.testing.assert_array_equal(
            label_tile_points(failing, xyz, occupancy, cubes=cubes), eager
        )
    assert "running it eagerly" in caplog.text and not failing.compiled


def test_a_tile_with_overflowing_logits_is_labelled_in_float32(
    trained: Any, cnn_scans: Path
) -> None:
    model = _model(POINT, trained.network)
    xyz = np.asarray(read_points(cnn_scans / "test.txt").xyz)[:300]
    cubes = POINT.cubes
    occupancy = build_occupancy(
        xyz, origin=model.grid_origin(xyz[0]), voxel_sizes_m=cubes.voxel_sizes_m, centring="point"
    )
    network = _inference(model, "never", None)
    expected = label_tile_points(network, xyz, occupancy, cubes=cubes)
    reference = network.reference

    def overflowing(batch: torch.Tensor) -> torch.Tensor:
        logits = reference(batch)
        logits[:5, 0] = float("inf")  # as float16 would, past 65,504
        return logits

    network.fast = overflowing
    classify = network.classify
    calls: list[bool] = []

    def spy(batch: torch.Tensor, *, precise: bool = False) -> Any:
        calls.append(precise)
        return classify(batch, precise=precise)

    network.classify = spy  # type: ignore[method-assign]
    np.testing.assert_array_equal(label_tile_points(network, xyz, occupancy, cubes=cubes), expected)
    assert not calls[0] and calls[-1]  # the tile was labelled again, in float32


def test_the_producer_runs_ahead_boundedly_and_stops_with_its_consumer() -> None:
    made: list[int] = []
    finished = threading.Event()

    def produce() -> Iterator[int]:
        try:
            for item in range(1000):
                made.append(item)
                yield item
        finally:
            finished.set()

    with Prefetched(produce, depth=2) as items:
        assert next(items) == 0
        assert next(items) == 1
    assert finished.is_set() and len(made) <= 5  # 2 taken, 2 queued, 1 being put

    def failing() -> Iterator[int]:
        yield 1
        raise ValueError("tile 7: broken")

    with Prefetched(failing) as items:
        assert next(items) == 1
        with pytest.raises(ValueError, match="tile 7: broken"):
            next(items)


cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
HALF_TIE = 0.05
"""Float16 logits closer than this (relative to the larger logit) may order either way."""


def assert_same_labels_but_half_ties(labels: np.ndarray, logits: np.ndarray) -> None:
    expected = logits.argmax(axis=1) + 1
    differ = np.flatnonzero(labels != expected)
    top = np.sort(logits, axis=1)
    scale = 1.0 + np.abs(top[differ, -1])
    assert np.all(top[differ, -1] - top[differ, -2] < HALF_TIE * scale), differ
    assert differ.size <= 0.01 * labels.size


@pytest.mark.gpu
@cuda
@pytest.mark.parametrize("compile_mode", ["never", "always"])
def test_cuda_labels_equal_float32_labels_but_float16_ties(
    trained: Any, cnn_scans: Path, compile_mode: str
) -> None:
    cloud = read_points(cnn_scans / "test.txt")
    xyz = np.asarray(cloud.xyz)
    for config in (POINT, TINY):
        model = _model(config, copy.deepcopy(trained.network), compile=compile_mode)
        logits = reference_logits(model, xyz)
        model.to("cuda")
        assert model.inference.dtype == torch.float16
        labels = model.label_cloud(cloud)  # cubes made on the GPU, float16 network
        assert_same_labels_but_half_ties(labels, logits)
        assert model.inference.compiled == (compile_mode == "always")
