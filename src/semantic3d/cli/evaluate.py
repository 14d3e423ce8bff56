"""``semantic3d validate | evaluate | stats | agreement``: the benchmark's evaluation commands.

Thin shells over :mod:`semantic3d.evaluation`: parse arguments, call the library with a
progress bar, present the result. An invalid submission prints every problem and exits
with code 1; other package errors print one red line and exit with code 2.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence
from enum import StrEnum
from pathlib import Path
from typing import TYPE_CHECKING

import typer

from semantic3d.cli import console as ui
from semantic3d.cli.cluster import open_cluster, scheduler_option, workers_option
from semantic3d.cli.console import (
    escape,
    fail,
    guarded,
    plural,
    progress_bar,
    refuse_existing,
    threads_option,
    write_atomically,
)

if TYPE_CHECKING:
    import numpy as np
    from rich.table import Table

    from semantic3d.core.errors import SubmissionError
    from semantic3d.evaluation.agreement import AgreementResult
    from semantic3d.evaluation.challenge import Challenge
    from semantic3d.evaluation.result import EvaluationResult
    from semantic3d.evaluation.stats import ClassStatistics

#: The defaults of :mod:`semantic3d.evaluation.agreement`, repeated so that building the
#: app does not import numpy (a test keeps them equal).
DEFAULT_MAX_DISTANCE_M = 0.05
DEFAULT_TILE_SIZE_M = 10.0

_OVERWRITE_HELP = "Replace output files that already exist (refused otherwise)."

INVALID_SUBMISSION_EXIT = 1


class ChallengeName(StrEnum):
    """Challenges selectable on the command line."""

    SEMANTIC_8 = "semantic-8"
    REDUCED_8 = "reduced-8"
    CUSTOM = "custom"


_CHALLENGE_HELP = (
    "semantic-8 or reduced-8 (official names and line counts), or custom: every "
    "*.labels file of --gt is a scan and the submission uses the same file names."
)


def _challenge(name: ChallengeName, gt: Path | None, *, need_ground_truth: bool) -> Challenge:
    from semantic3d.evaluation.challenge import custom_challenge, load_challenge

    if name is ChallengeName.CUSTOM:
        if gt is None:
            raise fail("--challenge custom needs --gt DIR (the folder of ground-truth .labels)")
        return custom_challenge(gt)
    if gt is None and need_ground_truth:
        raise fail(f"--challenge {name.value} needs --gt DIR to evaluate (ground truth)")
    return load_challenge(name.value, ground_truth_root=gt)


def _print_invalid(exc: SubmissionError) -> typer.Exit:
    count = len(exc.problems)
    ui.err_console.print(
        f"[bold red]invalid submission[/] {escape(exc.source or '')}: "
        f"{count} problem{'s' if count != 1 else ''}",
        highlight=False,
    )
    for problem in exc.problems:
        ui.err_console.print(f"  [red]-[/] {escape(problem)}", highlight=False, soft_wrap=True)
    return typer.Exit(code=INVALID_SUBMISSION_EXIT)


def validate(
    submission: Path = typer.Argument(..., help="A .zip archive or a folder of .labels files."),
    challenge: ChallengeName = typer.Option(
        ChallengeName.CUSTOM, "--challenge", "-c", help=_CHALLENGE_HELP
    ),
    gt: Path | None = typer.Option(
        None, "--gt", file_okay=False, help="Folder of ground-truth .labels files."
    ),
    threads: int | None = threads_option(),
) -> None:
    """Check a submission: names, archive safety, values 1..8, line counts (all problems)."""
    with guarded():
        from semantic3d.core.errors import SubmissionError
        from semantic3d.evaluation.submission import validate_submission

        spec = _challenge(challenge, gt, need_ground_truth=False)
        with progress_bar(bytes_=True) as progress:
            task = progress.add_task(f"checking {submission.name}", total=None)
            try:
                validate_submission(
                    submission,
                    challenge=spec,
                    progress=lambda done, total: progress.update(task, completed=done, total=total),
                )
            except SubmissionError as exc:
                progress.stop()
                raise _print_invalid(exc) from None
        ui.console.print(
            f"[green]valid[/]: {escape(str(submission))} holds the "
            f"{plural(len(spec.scans), 'file')} of {escape(spec.name)}",
            highlight=False,
        )


def _format(value: float) -> str:
    return "absent" if math.isnan(value) else f"{value:.3f}"


def _transposed(title: str, header: Sequence[str], rows: Sequence[Sequence[str]]) -> Table:
    """A table of ``rows`` (one per column of the output) with ``header`` down the side.

    The paper's tables have 12 columns, too wide for a terminal; one column per result
    (or split) and one row per quantity fits 80 characters.
    """
    from rich.table import Table

    table = Table(title=title)
    table.add_column(header[0], style="bold")
    for row in rows:
        table.add_column(row[0], justify="right")
    for i, name in enumerate(header[1:], start=1):
        table.add_row(name, *(row[i] for row in rows))
    return table


def _results_table(result: EvaluationResult) -> Table:
    from semantic3d.evaluation.report import results_table_rows

    header, rows = results_table_rows([result])
    return _transposed(f"{result.challenge} (protocol v{result.protocol_version})", header, rows)


def evaluate(
    gt: Path = typer.Option(
        ..., "--gt", exists=True, file_okay=False, help="Folder of ground-truth .labels files."
    ),
    pred: Path = typer.Option(
        ..., "--pred", exists=True, help="The submission: a .zip or a folder of .labels files."
    ),
    challenge: ChallengeName = typer.Option(
        ChallengeName.CUSTOM, "--challenge", "-c", help=_CHALLENGE_HELP
    ),
    json_path: Path | None = typer.Option(
        None, "--json", dir_okay=False, help="Write the full result (per scan included) as JSON."
    ),
    report: Path | None = typer.Option(
        None, "--report", dir_okay=False, help="Write a self-contained HTML report."
    ),
    markdown: Path | None = typer.Option(
        None, "--markdown", dir_okay=False, help="Write a Markdown report."
    ),
    method: str | None = typer.Option(None, "--method", help="Method name shown in reports."),
    runtime_s: float | None = typer.Option(
        None, "--runtime-s", min=0, help="The method's processing time in seconds (column T)."
    ),
    hardware: str | None = typer.Option(None, "--hardware", help="What the method ran on."),
    overwrite: bool = typer.Option(False, "--overwrite", help=_OVERWRITE_HELP),
    runtime_alias: float | None = typer.Option(None, "--runtime", min=0, hidden=True),
    scheduler: str | None = scheduler_option(),
    workers: int | None = workers_option(),
    threads: int | None = threads_option(),
) -> None:
    """Evaluate a submission against ground truth: IoU per class, mIoU, OA.

    A folder submission may hold the NAME.labels.json run records that `baseline ...
    predict` writes beside its labels; they are not part of the submission. A zip is held
    to the protocol: label files only.
    """
    with guarded():
        from semantic3d.core.classes import CLASSES
        from semantic3d.core.errors import SubmissionError, require
        from semantic3d.evaluation.evaluate import evaluate_submission
        from semantic3d.evaluation.report import write_html, write_json, write_markdown
        from semantic3d.evaluation.result import MethodInfo

        if runtime_s is None:
            runtime_s = runtime_alias
        if report is not None:
            require("matplotlib", "viz")  # the HTML report's figures; fail before the work
        outputs = [path for path in (json_path, report, markdown) if path is not None]
        refuse_existing(outputs, overwrite=overwrite)
        spec = _challenge(challenge, gt, need_ground_truth=True)
        info = None
        if method is not None or runtime_s is not None or hardware is not None:
            info = MethodInfo(name=method or pred.stem, runtime_s=runtime_s, hardware=hardware)
        with (
            open_cluster(scheduler, workers) as cluster,
            progress_bar(bytes_=True) as progress,
        ):
            task = progress.add_task(f"evaluating {pred.name}", total=None)
            try:
                result = evaluate_submission(
                    pred,
                    challenge=spec,
                    method=info,
                    progress=lambda done, total: progress.update(task, completed=done, total=total),
                    map_scans=None if cluster is None else cluster.map,
                )
            except SubmissionError as exc:
                progress.stop()
                raise _print_invalid(exc) from None
        ui.console.print(_results_table(result))
        absent = [CLASSES[i].name for i in result.scores.absent_indices]
        if absent:
            ui.console.print(f"absent (left out of mIoU): {', '.join(absent)}", highlight=False)
        ui.console.print(f"{result.n_points:,} labelled points scored", highlight=False)
        for path, writer, what in (
            (json_path, write_json, "JSON"),
            (markdown, write_markdown, "Markdown"),
            (report, write_html, "HTML report"),
        ):
            if path is not None:
                write_atomically(path, functools.partial(_write_report, writer, result))
                ui.console.print(f"wrote {what} to {path}", highlight=False)


def _write_report(
    writer: Callable[[Path, EvaluationResult], None], result: EvaluationResult, path: Path
) -> None:
    writer(path, result)


def _stats_table(statistics: ClassStatistics) -> Table:
    from semantic3d.evaluation.stats import class_table

    header, rows = class_table(statistics)
    shown = [[row[0], row[1], *(f"{int(v):,}" for v in row[2:])] for row in rows]
    return _transposed("points per class", header, shown)


def stats(
    folder: Path = typer.Argument(
        ..., exists=True, file_okay=False, help="A folder of .labels files (searched recursively)."
    ),
    plot: Path | None = typer.Option(
        None, "--plot", dir_okay=False, help="Write the log-scale bar chart (PNG)."
    ),
    overwrite: bool = typer.Option(False, "--overwrite", help=_OVERWRITE_HELP),
) -> None:
    """Points per class per split (benchmark splits by scan name, else custom)."""
    with guarded():
        from semantic3d.core.errors import require
        from semantic3d.evaluation.stats import compute_class_statistics

        if plot is not None:
            require("matplotlib", "viz")
        refuse_existing([plot] if plot is not None else [], overwrite=overwrite)
        with progress_bar(bytes_=True) as progress:
            task = progress.add_task(f"counting {folder.name}", total=None)
            statistics = compute_class_statistics(
                folder,
                progress=lambda done, total: progress.update(task, completed=done, total=total),
            )
        ui.console.print(_stats_table(statistics))
        if plot is not None:
            from semantic3d.viz.plots import figure_to_png, plot_class_histogram

            figure = plot_class_histogram(statistics.class_counts_by_split())
            png = figure_to_png(figure)
            write_atomically(plot, lambda temp: temp.write_bytes(png))
            ui.console.print(f"wrote {plot}", highlight=False)


def _agreement_table(result: AgreementResult) -> Table:
    from rich.table import Table

    from semantic3d.core.classes import CLASSES

    # One column per direction, one row per quantity: fits an 80-column terminal.
    table = Table(title=f"label agreement (nearest neighbour within {result.max_distance_m} m)")
    table.add_column("")
    for direction in result.directions:
        table.add_column(direction.name, justify="right")
    directions = result.directions
    table.add_row(
        "matched points",
        *(f"{d.n_matched:,} ({_percent(d.matched_fraction)})" for d in directions),
    )
    table.add_row("mIoU", *(_format(d.scores.mean_iou) for d in directions))
    table.add_row("OA", *(_format(d.scores.overall_accuracy) for d in directions), end_section=True)
    for i, cls in enumerate(CLASSES):
        excluded = cls.value in result.excluded_values
        table.add_row(
            f"IoU {cls.value} {cls.name}",
            *("excluded" if excluded else _format(float(d.scores.iou[i])) for d in directions),
        )
    return table


def _percent(value: float) -> str:
    return "n/a" if math.isnan(value) else f"{100 * value:.1f} %"


def agreement(
    a_points: Path = typer.Argument(..., exists=True, dir_okay=False, help="Scan A points."),
    a_labels: Path = typer.Argument(..., exists=True, dir_okay=False, help="Scan A labels."),
    b_points: Path = typer.Argument(..., exists=True, dir_okay=False, help="Scan B points."),
    b_labels: Path = typer.Argument(..., exists=True, dir_okay=False, help="Scan B labels."),
    max_distance: float = typer.Option(
        DEFAULT_MAX_DISTANCE_M, "--max-distance", min=0.0, help="Matching radius in metres."
    ),
    tile_size: float = typer.Option(
        DEFAULT_TILE_SIZE_M, "--tile-size", min=0.0, help="XY tile side in metres (memory)."
    ),
    plot: Path | None = typer.Option(
        None, "--plot", dir_okay=False, help="Write the per-class IoU plot of both directions."
    ),
    exclude_first: bool = typer.Option(
        False,
        "--exclude-first",
        help="Remove unlabelled points and scanning artefacts before the neighbour search "
        "(default: search among all points, then leave out their pairs; the paper does "
        "not say which order it used).",
    ),
    overwrite: bool = typer.Option(False, "--overwrite", help=_OVERWRITE_HELP),
    scheduler: str | None = scheduler_option(),
    workers: int | None = workers_option(),
    workdir: Path | None = typer.Option(
        None, "--workdir", help="Scratch folder for the tile stores (shared with the workers)."
    ),
    threads: int | None = threads_option(),
) -> None:
    """Label agreement of two overlapping scans: transfer labels A→B and B→A, score them."""
    if not (max_distance > 0 and tile_size > 0):
        raise fail(
            f"expected a positive --max-distance and --tile-size, found {max_distance} and "
            f"{tile_size}"
        )
    with guarded():
        from semantic3d.core.errors import require
        from semantic3d.evaluation.agreement import compute_label_agreement
        from semantic3d.io.formats import iter_points

        require("scipy", "sim")  # k-d trees; fail before reading the scans
        if plot is not None:
            require("matplotlib", "viz")
        refuse_existing([plot] if plot is not None else [], overwrite=overwrite)
        with open_cluster(scheduler, workers) as cluster, progress_bar() as progress:
            task = progress.add_task(f"reading {a_points.name} and {b_points.name}", total=None)
            result = compute_label_agreement(
                iter_points(a_points, labels_path=a_labels),
                iter_points(b_points, labels_path=b_labels),
                max_distance_m=max_distance,
                spill_directory=workdir,
                map_tiles=None if cluster is None else cluster.map,
                tile_size_m=tile_size,
                exclude_before_matching=exclude_first,
                progress=lambda done, total: progress.update(
                    task, description="matching tiles", completed=done, total=total
                ),
            )
        ui.console.print(_agreement_table(result))
        if plot is not None:
            from semantic3d.viz.plots import figure_to_png, plot_agreement

            ious: dict[str, Sequence[float] | np.ndarray] = {
                d.name: d.scores.iou for d in result.directions
            }
            png = figure_to_png(plot_agreement(ious))
            write_atomically(plot, lambda temp: temp.write_bytes(png))
            ui.console.print(f"wrote {plot}", highlight=False)


def register(app: typer.Typer) -> None:
    """Add ``validate``, ``evaluate``, ``stats`` and ``agreement`` to ``app``."""
    app.command("validate")(validate)
    app.command("evaluate")(evaluate)
    app.command("stats")(stats)
    app.command("agreement")(agreement)
