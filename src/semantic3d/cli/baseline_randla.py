"""``semantic3d baseline randla train | predict | cv``: the RandLA-Net baseline.

Thin shells over :mod:`semantic3d.baselines.randla`: parse arguments, call the library
with a progress bar, print a summary. torch is imported when a command runs.
"""

from __future__ import annotations

import dataclasses
import json
from enum import StrEnum
from pathlib import Path
from typing import TYPE_CHECKING, Any

import typer

from semantic3d.cli import console as ui
from semantic3d.cli.baseline_common import (
    CHECKPOINT_SUFFIX,
    OVERWRITE_HELP,
    SCANS_HELP,
    ChallengeChoice,
    DeviceChoice,
    challenge_option,
    cross_validation_document,
    data_option,
    label_scans,
    out_option,
    print_folds,
    scan_argument,
    scan_names,
    scans_and_target,
    training_bar,
)
from semantic3d.cli.cluster import scheduler_option, workers_option
from semantic3d.cli.console import (
    MARKUP_MODE,
    escape,
    fail,
    guarded,
    plural,
    progress_bar,
    refuse_existing,
    threads_option,
)

if TYPE_CHECKING:
    from semantic3d.baselines.randla.config import RandlaConfig

randla_app = typer.Typer(
    rich_markup_mode=MARKUP_MODE,
    help="RandLA-Net (Hu et al. 2020): random sampling, local spatial encoding, attentive "
    "pooling; scans of any size, tile by tile.",
    no_args_is_help=True,
)


class PresetChoice(StrEnum):
    """Starting configurations."""

    CPU = "cpu"
    PAPER = "paper"


_CONFIG_HELP = (
    'TOML configuration (preset = "cpu" | "paper"; sections inputs, blocks, network, '
    "training, prediction). Default: the cpu preset."
)
_PRESET_HELP = (
    "cpu (minutes on a laptop) or paper (Hu et al.'s Semantic3D settings); not with --config."
)
_BATCHES_HELP = "Train this many mini-batches instead of the configuration's."
_STAGES = {"clouds": "drawing the round's sub-clouds"}


def _config(
    path: Path | None, preset: PresetChoice | None, seed: int | None, batches: int | None
) -> RandlaConfig:
    from semantic3d.baselines.randla.config import load_config, preset_config

    if path is not None and preset is not None:
        raise fail("expected --config or --preset, found both")
    if path is not None:
        config = load_config(path)
    else:
        config = preset_config((preset or PresetChoice.CPU).value)
    changes: dict[str, Any] = {}
    if seed is not None:
        changes["seed"] = seed
    if batches is not None:
        changes["n_batches"] = batches
    if changes:
        config = dataclasses.replace(
            config, training=dataclasses.replace(config.training, **changes)
        )
    return config


@randla_app.command()
def train(
    data: Path = typer.Option(..., "--data", help="Folder of labelled scans (any format)."),
    out: Path = typer.Option(..., "--out", help="Model file to write."),
    scans: list[str] = typer.Option([], "--scans", help=SCANS_HELP),
    config_path: Path | None = typer.Option(None, "--config", help=_CONFIG_HELP),
    preset: PresetChoice | None = typer.Option(None, "--preset", help=_PRESET_HELP),
    batches: int | None = typer.Option(None, "--batches", min=1, help=_BATCHES_HELP),
    seed: int | None = typer.Option(None, "--seed", help="Override the training seed."),
    device: DeviceChoice = typer.Option(DeviceChoice.CPU, "--device", help="cpu or cuda."),
    resume: bool = typer.Option(
        False, "--resume", help="Continue from OUT.checkpoint (written every checkpoint_every)."
    ),
    workdir: Path | None = typer.Option(None, "--workdir", help="Scratch folder for tiles."),
    overwrite: bool = typer.Option(False, "--overwrite", help=OVERWRITE_HELP),
    threads: int | None = threads_option(),
) -> None:
    """Train RandLA-Net on labelled scans (sub-clouds drawn from their tiles), save the model.

    Writes OUT.checkpoint every [training] checkpoint_every batches; --resume continues
    from it with the same configuration and scans (the model is the one an uninterrupted
    run gives). The checkpoint is removed once the model is saved.
    """
    with guarded():
        refuse_existing([out], overwrite=overwrite)
        checkpoint = out.with_name(out.name + CHECKPOINT_SUFFIX)
        if not resume:
            refuse_existing([checkpoint], overwrite=overwrite)
        from semantic3d.baselines.common.device import resolve_device, use_cpu_threads
        from semantic3d.baselines.common.scans import find_labelled_scans
        from semantic3d.baselines.randla.network import count_parameters
        from semantic3d.baselines.randla.persistence import save_model
        from semantic3d.baselines.randla.training import train_randla_model

        config = _config(config_path, preset, seed, batches)
        resolve_device(device.value)
        use_cpu_threads()
        labelled = find_labelled_scans(data, names=scan_names(scans))
        with progress_bar() as bar:
            task = bar.add_task("tiling the training scans", total=config.training.n_batches)
            model = train_randla_model(
                labelled,
                config=config,
                device=device.value,
                checkpoint=checkpoint,
                resume=resume,
                workdir=workdir,
                progress=training_bar(bar, task, stages=_STAGES),
            )
        save_model(model, out)
        checkpoint.unlink(missing_ok=True)
        ui.console.print(
            f"trained on {plural(len(labelled), 'scan')}, {model.n_batches_trained} batches of "
            f"{config.training.batch_size} sub-clouds in {model.training_time_s:.1f} s; "
            f"{count_parameters(model.network):,} parameters; saved {escape(str(out))}",
            highlight=False,
        )


@randla_app.command()
def predict(
    scan: Path | None = scan_argument(),
    model_path: Path = typer.Option(..., "--model", help="Model file from `train`."),
    data: Path | None = data_option(),
    out: Path | None = out_option(),
    challenge: ChallengeChoice | None = challenge_option(),
    device: DeviceChoice = typer.Option(DeviceChoice.CPU, "--device", help="cpu or cuda."),
    workdir: Path | None = typer.Option(None, "--workdir", help="Scratch folder for tiles."),
    overwrite: bool = typer.Option(False, "--overwrite", help=OVERWRITE_HELP),
    threads: int | None = threads_option(),
    scheduler: str | None = scheduler_option(),
    workers: int | None = workers_option(),
    votes: int | None = typer.Option(
        None,
        "--votes",
        min=1,
        max=64,
        help="Network passes per block whose class probabilities are averaged, each in its "
        "own random order and turned about z (default: the model's, 1); time grows with them.",
    ),
) -> None:
    """Label scans with a trained model: one SCAN, or every scan of --data.

    Writes NAME.labels and a NAME.labels.json run record (run time, hardware) per scan into
    ./predictions (or --out), as `baseline covariance predict` does. With --scheduler or
    --workers the tiles are labelled on a Dask cluster (same labels, byte for byte).
    """
    with guarded():
        from semantic3d.baselines.common.device import use_cpu_threads
        from semantic3d.baselines.common.submission import planned_outputs, refuse_existing_outputs
        from semantic3d.baselines.randla.persistence import load_model

        scans_to_label, target = scans_and_target(scan, data, out, challenge)
        refuse_existing_outputs(planned_outputs(target, scans_to_label), overwrite=overwrite)
        model = load_model(model_path, device=device.value)
        if votes is not None:
            model.configure_prediction(votes=votes)
        use_cpu_threads()
        label_scans(
            model,
            scans_to_label,
            target,
            workdir=workdir,
            overwrite=overwrite,
            challenge=None if challenge is None else challenge.value,
            cluster_options=(scheduler, workers),
        )


@randla_app.command()
def cv(
    data: Path = typer.Option(..., "--data", help="Folder of labelled scans."),
    scans: list[str] = typer.Option([], "--scans", help=SCANS_HELP),
    config_path: Path | None = typer.Option(None, "--config", help=_CONFIG_HELP),
    preset: PresetChoice | None = typer.Option(None, "--preset", help=_PRESET_HELP),
    folds: int = typer.Option(5, "--folds", min=2, help="Folds, grouped by scan."),
    batches: int | None = typer.Option(None, "--batches", min=1, help=_BATCHES_HELP),
    seed: int | None = typer.Option(None, "--seed", help="Override the training seed."),
    device: DeviceChoice = typer.Option(DeviceChoice.CPU, "--device", help="cpu or cuda."),
    workdir: Path | None = typer.Option(None, "--workdir", help="Scratch folder for tiles."),
    out: Path | None = typer.Option(None, "--out", help="Write the scores as JSON here."),
    overwrite: bool = typer.Option(False, "--overwrite", help=OVERWRITE_HELP),
    threads: int | None = threads_option(),
) -> None:
    """Cross-validate: train on all folds but one, label every point of the held-out scans."""
    with guarded():
        refuse_existing([out] if out is not None else [], overwrite=overwrite)
        from semantic3d.baselines.common.crossval import scan_folds
        from semantic3d.baselines.common.device import resolve_device, use_cpu_threads
        from semantic3d.baselines.common.scans import find_labelled_scans
        from semantic3d.baselines.common.submission import write_atomic_text
        from semantic3d.baselines.randla.crossval import cross_validate

        config = _config(config_path, preset, seed, batches)
        resolve_device(device.value)
        use_cpu_threads()
        labelled = find_labelled_scans(data, names=scan_names(scans))
        scan_folds([s.name for s in labelled], folds)  # refuse a bad fold count before work
        with progress_bar() as bar:
            task = bar.add_task("fold 1", total=config.training.n_batches)
            result = cross_validate(
                labelled,
                config=config,
                n_folds=folds,
                device=device.value,
                workdir=workdir,
                progress=training_bar(bar, task, stages=_STAGES),
                on_fold=lambda number, fold: bar.reset(task),
            )
        print_folds(
            result,
            title=f"{folds} folds grouped by scan, {config.training.n_batches} batches",
        )
        if out is not None:
            document = cross_validation_document(
                result, n_folds=folds, n_batches=config.training.n_batches
            )
            write_atomic_text(out, json.dumps(document, indent=2) + "\n")
