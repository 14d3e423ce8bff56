"""``semantic3d baseline cnn train | predict | cv``: the paper's 3D CNN baseline (DeepNet).

Thin shells over :mod:`semantic3d.baselines.cnn`: parse arguments, call the library with
a progress bar, print a summary. torch is imported when a command runs.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import signal
import threading
from collections.abc import Iterator
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
    data_option,
    out_option,
    print_runs,
    scan_argument,
    scan_names,
    scans_and_target,
    scans_progress,
)
from semantic3d.cli.cluster import open_cluster, scheduler_option, workers_option
from semantic3d.cli.console import (
    MARKUP_MODE,
    escape,
    guarded,
    plural,
    progress_bar,
    refuse_existing,
    threads_option,
)

if TYPE_CHECKING:
    from semantic3d.baselines.cnn.config import CnnConfig
    from semantic3d.baselines.common.prediction import Predictor

cnn_app = typer.Typer(
    rich_markup_mode=MARKUP_MODE,
    help="3D CNN baseline (DeepNet, the paper's): multi-scale occupancy cubes + 3D CNN.",
    no_args_is_help=True,
)

_CONFIG_HELP = (
    'TOML configuration (preset = "paper" | "cpu-short"; sections cubes, network, training, '
    "prediction). Default: the paper's values where it gives them."
)
_BATCHES_HELP = "Train this many mini-batches instead of the configuration's (a shortened run)."


def _config(path: Path | None, seed: int | None, batches: int | None) -> CnnConfig:
    from semantic3d.baselines.cnn.config import CnnConfig, load_config

    config = load_config(path) if path is not None else CnnConfig()
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


def _training_bar(bar: Any, task: Any) -> Any:
    def update(state: Any) -> None:
        if state.stage == "cubes":  # training waits for a round's cubes
            made = (
                f": {state.cube_points:,} of {state.cube_points_total:,} points"
                if state.cube_points_total
                else ""
            )
            bar.update(
                task,
                completed=state.batch,
                total=state.n_batches,
                description=f"batch {state.batch}: making the next round's cubes{made}",
            )
            return
        bar.update(
            task,
            completed=state.batch,
            total=state.n_batches,
            description=(
                f"batch {state.batch}: loss {state.loss:.3f}, "
                f"balanced accuracy {state.balanced_accuracy:.3f}"
            ),
        )

    return update


@cnn_app.command()
def train(
    data: Path = typer.Option(..., "--data", help="Folder of labelled scans (any format)."),
    out: Path = typer.Option(..., "--out", help="Model file to write."),
    scans: list[str] = typer.Option([], "--scans", help=SCANS_HELP),
    config_path: Path | None = typer.Option(None, "--config", help=_CONFIG_HELP),
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
    """Train DeepNet on labelled scans (class-balanced batches) and save the model.

    Writes OUT.checkpoint every [training] checkpoint_every batches and on Ctrl-C; --resume
    continues from it with the same configuration and scans (the model is the one an
    uninterrupted run gives). The checkpoint is removed once the model is saved.
    """
    with guarded():
        refuse_existing([out], overwrite=overwrite)
        checkpoint = out.with_name(out.name + CHECKPOINT_SUFFIX)
        if not resume:
            refuse_existing([checkpoint], overwrite=overwrite)
        from semantic3d.baselines.cnn.network import count_parameters
        from semantic3d.baselines.cnn.persistence import save_model
        from semantic3d.baselines.cnn.training import TrainingInterrupted, train_cnn_model
        from semantic3d.baselines.common.scans import find_labelled_scans

        config = _config(config_path, seed, batches)
        scheduled = _config(config_path, seed, None).training.n_batches
        short = _short_run(config.training.n_batches, scheduled)
        labelled = find_labelled_scans(data, names=scan_names(scans))
        if short:
            ui.console.print(short, highlight=False)
        stop = threading.Event()
        try:
            with progress_bar() as bar, _stop_on_ctrl_c(stop):
                task = bar.add_task("tiling the training scans", total=config.training.n_batches)
                model = train_cnn_model(
                    labelled,
                    config=config,
                    device=device.value,
                    checkpoint=checkpoint,
                    resume=resume,
                    workdir=workdir,
                    progress=_training_bar(bar, task),
                    stop=stop,
                )
        except TrainingInterrupted as stopped:
            ui.console.print(
                f"interrupted after {stopped.batch} batches; checkpoint "
                f"{escape(str(checkpoint))}: continue with --resume",
                highlight=False,
            )
            raise typer.Exit(130) from None
        save_model(model, out)
        checkpoint.unlink(missing_ok=True)
        ui.console.print(
            f"trained on {plural(len(labelled), 'scan')}, {model.n_batches_trained} batches of "
            f"{config.training.batch_size}{' (a short run)' if short else ''} in "
            f"{model.training_time_s:.1f} s; {count_parameters(model.network):,} parameters; "
            f"saved {escape(str(out))}",
            highlight=False,
        )


def _short_run(n_batches: int, scheduled: int) -> str:
    """The line saying a ``--batches`` run is shorter than its schedule ('' if it is not)."""
    if n_batches >= scheduled:
        return ""
    return (
        f"a short run: {n_batches:,} batches of the configuration's {scheduled:,} "
        f"(the paper trains 74,700); the model is not the schedule's"
    )


@contextlib.contextmanager
def _stop_on_ctrl_c(stop: threading.Event) -> Iterator[None]:
    """The first Ctrl-C sets ``stop`` (training ends after its batch with a checkpoint),
    a second one interrupts at once. Only the main thread can take signals; elsewhere
    Ctrl-C keeps its default."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handle(signum: int, frame: object) -> None:
        if stop.is_set():
            raise KeyboardInterrupt
        stop.set()

    previous = signal.signal(signal.SIGINT, handle)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


@cnn_app.command()
def predict(
    scan: Path | None = scan_argument(),
    model_path: Path = typer.Option(..., "--model", help="Model file from `train`."),
    data: Path | None = data_option(),
    out: Path | None = out_option(),
    challenge: ChallengeChoice | None = challenge_option(),
    device: DeviceChoice = typer.Option(DeviceChoice.CPU, "--device", help="cpu or cuda."),
    workdir: Path | None = typer.Option(None, "--workdir", help="Scratch folder for tiles."),
    overwrite: bool = typer.Option(False, "--overwrite", help=OVERWRITE_HELP),
    scheduler: str | None = scheduler_option(),
    workers: int | None = workers_option(),
    threads: int | None = threads_option(),
) -> None:
    """Label scans with a trained model: one SCAN, or every scan of --data.

    Writes NAME.labels and a NAME.labels.json run record (run time, hardware) per scan into
    ./predictions (or --out), as `baseline covariance predict` does. With --scheduler or
    --workers the tiles are labelled on a Dask cluster (same labels, byte for byte).
    """
    with guarded():
        from semantic3d.baselines.cnn.persistence import load_model
        from semantic3d.baselines.common.prediction import predict_scans
        from semantic3d.baselines.common.submission import (
            is_zip_output,
            refuse_unsafe_outputs,
        )

        scans_to_label, target = scans_and_target(scan, data, out, challenge)
        refuse_unsafe_outputs(target, scans_to_label, overwrite=overwrite)
        model = load_model(model_path, device=device.value)
        with open_cluster(scheduler, workers) as cluster, progress_bar() as bar:
            task, update = scans_progress(bar, scans_to_label)

            predictor: Predictor = model
            if cluster is not None:  # tiles labelled by the workers (same labels)
                from semantic3d.scale.predict_cnn import ClusterCnnPredictor

                predictor = ClusterCnnPredictor(model, cluster)
            result = predict_scans(
                predictor,
                scans_to_label,
                target,
                workdir=workdir,
                progress=update,
                overwrite=overwrite,
            )
            bar.update(task, completed=result.n_points, total=result.n_points)
        print_runs(
            result,
            zipped=is_zip_output(target),
            challenge=None if challenge is None else challenge.value,
        )


@cnn_app.command()
def cv(
    data: Path = typer.Option(..., "--data", help="Folder of labelled scans."),
    scans: list[str] = typer.Option([], "--scans", help=SCANS_HELP),
    config_path: Path | None = typer.Option(None, "--config", help=_CONFIG_HELP),
    folds: int = typer.Option(5, "--folds", min=2, help="Folds, grouped by scan."),
    points_per_scan: int | None = typer.Option(
        None,
        "--points-per-scan",
        min=1,
        help="Label a random sample of this many points per held-out scan (default all).",
    ),
    batches: int | None = typer.Option(None, "--batches", min=1, help=_BATCHES_HELP),
    seed: int | None = typer.Option(None, "--seed", help="Override the training seed."),
    device: DeviceChoice = typer.Option(DeviceChoice.CPU, "--device", help="cpu or cuda."),
    workdir: Path | None = typer.Option(None, "--workdir", help="Scratch folder for tiles."),
    out: Path | None = typer.Option(None, "--out", help="Write the scores as JSON here."),
    overwrite: bool = typer.Option(False, "--overwrite", help=OVERWRITE_HELP),
    threads: int | None = threads_option(),
) -> None:
    """Cross-validate: train on all folds but one, label the held-out scans, score them."""
    with guarded():
        refuse_existing([out] if out is not None else [], overwrite=overwrite)
        from rich.table import Table

        from semantic3d.baselines.cnn.crossval import cross_validate, scan_folds
        from semantic3d.baselines.common.scans import find_labelled_scans
        from semantic3d.baselines.common.submission import write_atomic_text

        config = _config(config_path, seed, batches)
        labelled = find_labelled_scans(data, names=scan_names(scans))
        scan_folds([s.name for s in labelled], folds)  # refuse a bad fold count before work
        with progress_bar() as bar:
            task = bar.add_task("fold 1", total=config.training.n_batches)
            result = cross_validate(
                labelled,
                config=config,
                n_folds=folds,
                points_per_scan=points_per_scan,
                device=device.value,
                workdir=workdir,
                progress=_training_bar(bar, task),
                on_fold=lambda number, fold: bar.reset(task),
            )
        table = Table(title=f"{folds} folds grouped by scan, {config.training.n_batches} batches")
        for column in ("held out", "points", "mIoU", "OA", "train s", "predict s"):
            table.add_column(column, justify="right")
        for fold in result.folds:
            scores = fold.scores
            table.add_row(
                ", ".join(fold.test_scans),
                f"{fold.n_points:,}",
                f"{scores.mean_iou:.3f}",
                f"{scores.overall_accuracy:.3f}",
                f"{fold.training_time_s:.0f}",
                f"{fold.prediction_time_s:.0f}",
            )
        ui.console.print(table)
        pooled = result.scores
        ui.console.print(
            f"pooled: mIoU {pooled.mean_iou:.3f}, OA {pooled.overall_accuracy:.3f}",
            highlight=False,
        )
        if out is not None:
            document = {
                "n_folds": folds,
                "n_batches": config.training.n_batches,
                "points_per_scan": points_per_scan,
                "mean_iou": pooled.mean_iou,
                "overall_accuracy": pooled.overall_accuracy,
                "folds": [
                    {
                        "train_scans": list(f.train_scans),
                        "test_scans": list(f.test_scans),
                        "n_points": f.n_points,
                        "mean_iou": f.scores.mean_iou,
                        "overall_accuracy": f.scores.overall_accuracy,
                        "confusion": f.confusion.tolist(),
                        "training_time_s": f.training_time_s,
                        "prediction_time_s": f.prediction_time_s,
                    }
                    for f in result.folds
                ],
            }
            write_atomic_text(out, json.dumps(document, indent=2) + "\n")
