"""What every ``semantic3d baseline <name>`` command shares: options, choices, the scans a
``predict`` labels and where it writes, and the summary it prints.

Each baseline's command module (``baseline.py`` for the covariance baseline,
``baseline_cnn.py``, ``baseline_image.py``, ...) imports these; none imports another
baseline's module. Nothing heavy is imported here (the app is built from these modules at
start-up).
"""

from __future__ import annotations

from enum import StrEnum
from pathlib import Path
from typing import TYPE_CHECKING, Any

import typer

from semantic3d.cli import console as ui
from semantic3d.cli.console import escape, fail, plural

if TYPE_CHECKING:
    from collections.abc import Sequence

    from rich.progress import Progress, TaskID

    from semantic3d.baselines.common.crossval import CrossValidationResult
    from semantic3d.baselines.common.prediction import RunProgress
    from semantic3d.baselines.common.run import PredictionRunSet
    from semantic3d.baselines.common.submission import ScanToLabel

__all__ = [
    "CHECKPOINT_SUFFIX",
    "DEFAULT_PREDICTIONS",
    "OVERWRITE_HELP",
    "SCANS_HELP",
    "ChallengeChoice",
    "DeviceChoice",
    "challenge_option",
    "cross_validation_document",
    "data_option",
    "label_scans",
    "out_option",
    "print_folds",
    "print_runs",
    "scan_argument",
    "scan_names",
    "scans_and_target",
    "scans_progress",
    "training_bar",
]

SCANS_HELP = "Scan names (NAME of NAME.txt) to use, repeatable or comma-separated; default all."
OVERWRITE_HELP = "Replace outputs that already exist (refused otherwise)."

#: Where ``predict`` writes when no --out is given (relative to the working directory).
DEFAULT_PREDICTIONS = Path("predictions")

CHECKPOINT_SUFFIX = ".checkpoint"
"""The checkpoint of ``train --out MODEL`` is ``MODEL.checkpoint``."""


class ChallengeChoice(StrEnum):
    """Test challenges whose scans ``predict --data`` can label under official names."""

    SEMANTIC_8 = "semantic-8"
    REDUCED_8 = "reduced-8"


class DeviceChoice(StrEnum):
    """Where a network runs."""

    CPU = "cpu"
    CUDA = "cuda"


def scan_argument() -> Any:
    """``predict``'s optional SCAN argument (one scan; or ``--data``)."""
    return typer.Argument(None, help="One scan to label (any format); or use --data.")


def data_option() -> Any:
    """``predict``'s ``--data DIR``: every scan of a folder."""
    return typer.Option(
        None, "--data", file_okay=False, help="Label every scan of this folder (NAME.txt)."
    )


def out_option() -> Any:
    """``predict``'s ``--out``: a folder, a zip, or for one scan a ``.labels`` file."""
    return typer.Option(
        None,
        "--out",
        help="A folder (default ./predictions), a zip archive ready for `submit` (ends in "
        ".zip) or, for one scan, a .labels file.",
    )


def challenge_option() -> Any:
    """``predict``'s ``--challenge``: the challenge's scans under their official names."""
    return typer.Option(
        None,
        "--challenge",
        "-c",
        help="With --data: label the challenge's scans under their official submission "
        "names (default: every NAME.txt, as NAME.labels).",
    )


def scan_names(scans: list[str]) -> list[str]:
    """The names of repeatable, comma-separated ``--scans`` options."""
    return [name.strip() for item in scans for name in item.split(",") if name.strip()]


def scans_and_target(
    scan: Path | None, data: Path | None, out: Path | None, challenge: ChallengeChoice | None
) -> tuple[tuple[ScanToLabel, ...], Path]:
    """What ``predict`` labels and the folder or zip it writes to."""
    from semantic3d.baselines.common.submission import ScanToLabel, find_scans_to_label

    target = out if out is not None else DEFAULT_PREDICTIONS
    if data is not None:
        if scan is not None:
            raise fail("expected one SCAN argument or --data DIR, found both")
        if target.suffix == ".labels":
            raise fail(f"{target}: with --data, --out is a folder or a .zip archive")
        challenge_name = None if challenge is None else challenge.value
        return find_scans_to_label(data, challenge=challenge_name), target
    if scan is None:
        raise fail("expected one SCAN argument or --data DIR, found neither")
    if challenge is not None:
        raise fail("--challenge applies to --data DIR (a folder of the challenge's scans)")
    if not scan.is_file():
        raise fail(f"{scan}: expected a scan file (x y z intensity r g b lines), found none")
    if target.suffix == ".labels":  # one scan into a named labels file
        return (ScanToLabel(scan.stem, scan, target.name),), target.parent
    return (ScanToLabel(scan.stem, scan, scan.stem + ".labels"),), target


def print_runs(result: PredictionRunSet, *, zipped: bool, challenge: str | None) -> None:
    """One line per labelled scan, a total for many, and the ``submit`` line for a zip."""
    for run in result.runs:
        ui.console.print(
            f"{escape(Path(run.scan).name)}: {plural(run.n_points, 'point')} labelled in "
            f"{run.runtime_s:.1f} s ({run.points_per_second:,.0f} points/s"
            f"{', tiled' if run.tiled else ''}) -> {escape(run.labels_path)}",
            highlight=False,
            soft_wrap=True,
        )
    if len(result.runs) > 1 or zipped:
        ui.console.print(
            f"{plural(len(result.runs), 'scan')}, {plural(result.n_points, 'point')} in "
            f"{result.runtime_s:.1f} s -> {escape(result.out)}",
            highlight=False,
            soft_wrap=True,
        )
    if zipped:
        hardware = result.runs[0].hardware.describe() if result.runs else ""
        ui.console.print(
            "submit it with: semantic3d submit --server URL --token TOKEN "
            f"--challenge {challenge or 'NAME'} --method NAME --runtime-s {result.runtime_s:.0f} "
            f"--hardware {escape(repr(hardware))} {escape(result.out)}",
            highlight=False,
            soft_wrap=True,
        )


def training_bar(bar: Any, task: Any, *, stages: dict[str, str] | None = None) -> Any:
    """A progress callback for a network's training (a ``TrainingProgress`` per batch):
    the batch count, the round's loss and balanced accuracy; ``stages`` names what the
    bar says while a preparation stage runs (``{"clouds": "drawing sub-clouds"}``)."""
    named = stages or {}

    def update(state: Any) -> None:
        if state.stage != "train":
            description = named.get(state.stage, state.stage)
            bar.update(task, description=description, total=state.n_batches)
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


def print_folds(result: CrossValidationResult, *, title: str) -> None:
    """A table of a cross-validation's folds and its pooled scores."""
    from rich.table import Table

    table = Table(title=title)
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
        f"pooled: mIoU {pooled.mean_iou:.3f}, OA {pooled.overall_accuracy:.3f}", highlight=False
    )


def cross_validation_document(result: CrossValidationResult, **settings: Any) -> dict[str, Any]:
    """A cross-validation as JSON-ready values: ``settings``, pooled scores, every fold."""
    pooled = result.scores
    return {
        **settings,
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


def scans_progress(bar: Progress, scans: Sequence[ScanToLabel]) -> tuple[TaskID, RunProgress]:
    """A task of ``bar`` for a run over ``scans`` and the ``progress`` callback that moves
    it (``labelling NAME (2/7)``), for ``predict_scans`` and its kind."""
    task = bar.add_task(f"labelling {plural(len(scans), 'scan')}", total=None)

    def update(index: int, done: int, total: int) -> None:
        bar.update(
            task,
            description=f"labelling {scans[index].name} ({index + 1}/{len(scans)})",
            completed=done,
            total=total or None,
        )

    return task, update


def label_scans(
    model: Any,
    scans: tuple[ScanToLabel, ...],
    target: Path,
    *,
    workdir: Path | None,
    overwrite: bool,
    challenge: str | None,
    cluster_options: tuple[str | None, int | None] = (None, None),
) -> None:
    """``predict``'s work for a loaded model: label ``scans`` into ``target`` with a progress
    bar, on a Dask cluster when ``cluster_options`` (``--scheduler``, ``--workers``) name
    one, and print the runs.

    ``model`` is a :class:`~semantic3d.baselines.common.tiles.TiledModel`; on a cluster its
    tiles are labelled by the workers
    (:class:`~semantic3d.scale.predict_tiles.ClusterTilePredictor`, the same labels).
    """
    from semantic3d.baselines.common.prediction import predict_scans
    from semantic3d.baselines.common.submission import is_zip_output
    from semantic3d.cli.cluster import open_cluster
    from semantic3d.cli.console import progress_bar

    with open_cluster(*cluster_options) as cluster, progress_bar() as bar:
        task, update = scans_progress(bar, scans)

        predictor = model
        if cluster is not None:
            from semantic3d.scale.predict_tiles import ClusterTilePredictor

            predictor = ClusterTilePredictor(model, cluster)
        result = predict_scans(
            predictor, scans, target, workdir=workdir, progress=update, overwrite=overwrite
        )
        bar.update(task, completed=result.n_points, total=result.n_points)
    print_runs(result, zipped=is_zip_output(target), challenge=challenge)
