"""Training: the loss falls, the same seed gives the same model (rounds made by a producer
thread ahead of the steps), stopping and resuming gives it too."""

from __future__ import annotations

import contextlib
import dataclasses
import shutil
import threading
from pathlib import Path

import numpy as np
import pytest
import torch

from semantic3d.baselines.cnn import rounds
from semantic3d.baselines.cnn.cubes import build_occupancy
from semantic3d.baselines.cnn.rounds import make_round
from semantic3d.baselines.cnn.training import (
    CheckpointError,
    TrainingInterrupted,
    TrainingProgress,
    _tile_scan,
    train_cnn_model,
)
from semantic3d.baselines.common.scans import TrainingDataError, find_labelled_scans
from tests.baselines.cnn.conftest import TINY, TrainingRun, make_scene
from tests.baselines.conftest import write_scan


def _same_weights(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_loss_falls_and_balanced_accuracy_rises(training_run: TrainingRun) -> None:
    rounds = [p for p in training_run.progress if p.stage == "train" and p.batch % 10 == 0]
    assert [p.batch for p in rounds] == [10, 20, 30]
    assert rounds[-1].loss < 0.8 * rounds[0].loss
    assert rounds[-1].balanced_accuracy > rounds[0].balanced_accuracy
    assert training_run.model.label_values == (1, 3, 5, 8)
    assert training_run.model.n_batches_trained == 30


def test_same_seed_gives_the_same_model_and_resuming_the_uninterrupted_one(
    training_run: TrainingRun, cnn_scans: Path, tmp_path: Path
) -> None:
    scans = find_labelled_scans(cnn_scans, names=["train"])
    ten = dataclasses.replace(TINY, training=dataclasses.replace(TINY.training, n_batches=10))
    again = train_cnn_model(scans, config=ten)  # a fresh run of 10 batches, same seed
    saved = torch.load(training_run.checkpoint_10, weights_only=True)
    assert saved["batch"] == 10
    assert _same_weights(again.network.state_dict(), saved["network"])
    checkpoint = tmp_path / "run.checkpoint"
    shutil.copy(training_run.checkpoint_20, checkpoint)
    resumed = train_cnn_model(scans, config=TINY, checkpoint=checkpoint, resume=True)
    assert resumed.n_batches_trained == 30
    assert _same_weights(resumed.network.state_dict(), training_run.model.network.state_dict())
    assert not _same_weights(again.network.state_dict(), resumed.network.state_dict())
    other_seed = dataclasses.replace(TINY, training=dataclasses.replace(TINY.training, seed=1))
    with pytest.raises(CheckpointError, match="written with another configuration"):
        train_cnn_model(scans, config=other_seed, checkpoint=checkpoint, resume=True)


def test_bad_training_input_is_refused(cnn_scans: Path, tmp_path: Path) -> None:
    scans = find_labelled_scans(cnn_scans, names=["train"])
    with pytest.raises(CheckpointError, match="expected a checkpoint to resume from, found none"):
        train_cnn_model(scans, config=TINY, checkpoint=tmp_path / "none", resume=True)
    (tmp_path / "junk.checkpoint").write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="not a training checkpoint"):
        train_cnn_model(scans, config=TINY, checkpoint=tmp_path / "junk.checkpoint", resume=True)
    cloud = make_scene(3)
    write_scan(tmp_path / "one", "flat", cloud.with_labels(np.ones(cloud.n_points, np.uint8)))
    with pytest.raises(TrainingDataError, match=r"at least 2 labelled classes, found \[1\]"):
        train_cnn_model(find_labelled_scans(tmp_path / "one"), config=TINY)
    listed = dataclasses.replace(TINY, training=dataclasses.replace(TINY.training, classes=(1, 2)))
    with pytest.raises(TrainingDataError, match=r"class\(es\) 2 \(natural"):
        train_cnn_model(scans, config=listed)


def test_cross_validation_holds_out_each_scan_once(cnn_scans: Path) -> None:
    from semantic3d.baselines.cnn.crossval import cross_validate, scan_folds

    short = dataclasses.replace(TINY, training=dataclasses.replace(TINY.training, n_batches=3))
    result = cross_validate(
        find_labelled_scans(cnn_scans), config=short, n_folds=2, points_per_scan=200
    )
    assert [fold.test_scans for fold in result.folds] == [("test",), ("train",)]
    assert [fold.train_scans for fold in result.folds] == [("train",), ("test",)]
    assert all(fold.n_points == 200 for fold in result.folds)
    assert result.scores.n_points == 400
    with pytest.raises(TrainingDataError, match=r"expected 2\.\.2 folds for 2 scans, found 3"):
        scan_folds(["a", "b"], 3)


def test_stopping_writes_a_checkpoint_and_resuming_gives_the_uninterrupted_model(
    training_run: TrainingRun, cnn_scans: Path, tmp_path: Path
) -> None:
    scans = find_labelled_scans(cnn_scans, names=["train"])
    checkpoint = tmp_path / "run.checkpoint"
    stop = threading.Event()

    def progress(state: TrainingProgress) -> None:
        if state.batch == 7:  # Ctrl-C in the middle of round 0 (batches 0-9)
            stop.set()

    with pytest.raises(TrainingInterrupted) as stopped:
        train_cnn_model(scans, config=TINY, checkpoint=checkpoint, progress=progress, stop=stop)
    assert stopped.value.batch == 7 and stopped.value.checkpoint == checkpoint
    assert torch.load(checkpoint, weights_only=True)["batch"] == 7
    resumed = train_cnn_model(scans, config=TINY, checkpoint=checkpoint, resume=True)
    assert _same_weights(resumed.network.state_dict(), training_run.model.network.state_dict())
    stop.set()  # before the first round's cubes: a checkpoint of no batch
    with pytest.raises(TrainingInterrupted, match="stopped after 0 batches"):
        train_cnn_model(scans, config=TINY, checkpoint=tmp_path / "zero", stop=stop)
    assert torch.load(tmp_path / "zero", weights_only=True)["batch"] == 0


@pytest.mark.parametrize("centring", ["point", "corner"])
def test_cropped_tiles_give_a_round_the_cubes_of_whole_tiles(
    cnn_scans: Path, centring: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    small = dataclasses.replace(TINY.cubes, voxel_sizes_m=(0.05, 0.1, 0.2), centring=centring)
    config = dataclasses.replace(TINY, cubes=small)  # blocks of 1.6 m in 8 m tiles
    voxelised: list[int] = []

    def counting(xyz: np.ndarray, **options: object) -> object:
        voxelised.append(len(xyz))
        return build_occupancy(xyz, **options)  # type: ignore[arg-type]

    monkeypatch.setattr(rounds, "build_occupancy", counting)
    scans = find_labelled_scans(cnn_scans)
    with contextlib.ExitStack() as stack:
        tiled = [stack.enter_context(_tile_scan(scan, config, None)) for scan in scans]
        for index in (0, 1):
            whole = make_round(tiled, [1, 3, 5, 8], config, index, 2, device="cpu", crop=False)
            points_whole = sum(voxelised)
            voxelised.clear()
            cropped = make_round(tiled, [1, 3, 5, 8], config, index, 2, device="cpu", n_threads=2)
            assert sum(voxelised) < points_whole / 2  # the crop leaves most points out
            voxelised.clear()
            assert torch.equal(cropped.packed, whole.packed) and cropped.packed.any()
            assert torch.equal(cropped.targets, whole.targets)


@pytest.mark.parametrize("per_group", [None, 1, 3])
def test_a_rounds_tiles_filled_side_by_side_give_each_tiles_own_cubes(
    cnn_scans: Path, per_group: int | None, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The GPU path fills a round's point-centred cubes in one call, every tile moved to a
    band of its own: the cubes equal the compiled kernel's of each tile alone (run here on
    the CPU device through the same torch code), in one group or several."""
    small = dataclasses.replace(TINY.cubes, voxel_sizes_m=(0.05, 0.1, 0.2), centring="point")
    config = dataclasses.replace(TINY, cubes=small)
    if per_group is not None:  # as when fewer bands fit the keys' range
        monkeypatch.setattr(
            rounds,
            "_merged_groups",
            lambda n_tiles, _widest: [
                list(range(i, min(i + per_group, n_tiles))) for i in range(0, n_tiles, per_group)
            ],
        )
    scans = find_labelled_scans(cnn_scans)
    with contextlib.ExitStack() as stack:
        tiled = [stack.enter_context(_tile_scan(scan, config, None)) for scan in scans]
        for index in (0, 1, 2):
            compiled = make_round(tiled, [1, 3, 5, 8], config, index, 3, device="cpu")
            merged = make_round(
                tiled, [1, 3, 5, 8], config, index, 3, device="cpu", device_cubes=True
            )
            assert torch.equal(merged.packed, compiled.packed) and merged.packed.any()
            assert torch.equal(merged.targets, compiled.targets)


def test_a_round_is_cut_into_groups_that_keep_the_keys_in_range() -> None:
    small = dataclasses.replace(TINY.cubes, voxel_sizes_m=(0.05, 0.1, 0.2), centring="point")
    config = dataclasses.replace(TINY, cubes=small)
    rng = np.random.default_rng(0)
    tiles = []
    for _ in range(7):
        xyz = rng.uniform(-6.0, 6.0, (200, 3))
        tiles.append((None, (xyz[:5], build_occupancy(xyz, origin=np.zeros(3),
                      voxel_sizes_m=small.voxel_sizes_m, centring="point"))))  # fmt: skip
    widths = rounds._bands([t for _, t in tiles], config)[1]
    assert widths[0] >= 2 * (6.0 / 0.05) and widths[0] > widths[1] > widths[2]
    groups = rounds._merged_groups(len(tiles), max(widths))
    assert [i for g in groups for i in g] == list(range(7)) and len(groups) == 1
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(rounds, "MAX_CELL", 2 * widths[0])  # room for 3 bands of the finest
        groups = rounds._merged_groups(len(tiles), max(widths))
    assert [i for g in groups for i in g] == list(range(7))
    assert max(len(g) for g in groups) == 3


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_training_is_deterministic_and_resumes_to_the_uninterrupted_model(
    cnn_scans: Path, tmp_path: Path
) -> None:
    scans = find_labelled_scans(cnn_scans, names=["train"])
    config = dataclasses.replace(TINY, training=dataclasses.replace(TINY.training, n_batches=20))
    first = train_cnn_model(scans, config=config, device="cuda")  # rounds made on the GPU
    again = train_cnn_model(scans, config=config, device="cuda", report_every=3)
    assert _same_weights(first.network.state_dict(), again.network.state_dict())
    stop = threading.Event()

    def progress(state: TrainingProgress) -> None:
        if state.batch >= 13:
            stop.set()

    checkpoint = tmp_path / "cuda.checkpoint"
    with pytest.raises(TrainingInterrupted):
        train_cnn_model(
            scans,
            config=config,
            device="cuda",
            checkpoint=checkpoint,
            progress=progress,
            stop=stop,
            report_every=1,
        )
    resumed = train_cnn_model(
        scans, config=config, device="cuda", checkpoint=checkpoint, resume=True
    )
    assert _same_weights(resumed.network.state_dict(), first.network.state_dict())
