"""Training: the loss falls, the same seed gives the same model, resuming gives the model of
the uninterrupted run, and bad training data or checkpoints are refused."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch

from semantic3d.baselines.common.scans import TrainingDataError, find_labelled_scans
from semantic3d.baselines.common.training import CheckpointError
from semantic3d.baselines.randla.training import class_weights, train_randla_model
from tests.baselines.conftest import write_scan
from tests.baselines.randla.conftest import TrainingRun, make_scene, tiny_config


def test_a_tiny_run_learns(training_run: TrainingRun) -> None:
    batches = [p for p in training_run.progress if p.stage == "train"]
    assert [p.batch for p in batches] == list(range(1, 25))
    assert [p.stage for p in training_run.progress].count("clouds") == 6  # rounds of 4
    first, last = batches[3].loss, batches[-1].loss  # round means: batches 1-4, 21-24
    assert last < 0.8 * first, (first, last)
    assert batches[-1].balanced_accuracy > batches[3].balanced_accuracy
    model = training_run.model
    assert model.label_values == (1, 3, 5, 8) and model.n_batches_trained == 24


def test_resuming_from_a_checkpoint_gives_the_uninterrupted_model(
    training_run: TrainingRun, randla_scans: Path, tmp_path: Path
) -> None:
    checkpoint = tmp_path / "resume.checkpoint"
    checkpoint.write_bytes(training_run.checkpoint_8.read_bytes())
    resumed = train_randla_model(
        find_labelled_scans(randla_scans, names=["train"]),
        config=tiny_config(),
        checkpoint=checkpoint,
        resume=True,
    )
    assert resumed.n_batches_trained == 24
    for (name, mine), theirs in zip(
        resumed.network.state_dict().items(),
        training_run.model.network.state_dict().values(),
        strict=True,
    ):
        torch.testing.assert_close(mine, theirs, msg=name)


def test_a_checkpoint_of_another_configuration_is_refused(
    training_run: TrainingRun, randla_scans: Path
) -> None:
    other = tiny_config(training={"learning_rate": 0.5})
    with pytest.raises(CheckpointError, match="another configuration"):
        train_randla_model(
            find_labelled_scans(randla_scans, names=["train"]),
            config=other,
            checkpoint=training_run.checkpoint_8,
            resume=True,
        )


def test_training_data_without_what_the_configuration_asks_for_is_refused(
    tmp_path: Path,
) -> None:
    write_scan(tmp_path, "grey", make_scene(3))  # no colours
    scans = find_labelled_scans(tmp_path)
    with pytest.raises(TrainingDataError, match=r"grey\.txt: \[inputs\] rgb = true"):
        train_randla_model(scans, config=tiny_config(inputs={"rgb": True}))
    one_class = make_scene(3)
    write_scan(tmp_path / "one", "flat", one_class.with_labels(np.ones(one_class.n_points)))
    with pytest.raises(TrainingDataError, match="at least 2 labelled classes"):
        train_randla_model(find_labelled_scans(tmp_path / "one"), config=tiny_config())


def test_class_weights() -> None:
    totals = np.array([5, 80, 0, 15, 0, 5, 0, 0, 0])
    inverse = class_weights(totals, [1, 3, 5], "inverse")
    assert inverse.mean() == pytest.approx(1.0) and inverse[2] > inverse[1] > inverse[0]
    np.testing.assert_allclose(class_weights(totals, [1, 3, 5], "none"), 1.0)
    config = tiny_config()
    assert dataclasses.replace(config.training, class_weights="sqrt").class_weights == "sqrt"
