"""``semantic3d convert`` and ``semantic3d info``: point files between formats, and what they hold.

Both stream in constant memory through :mod:`semantic3d.io.formats`; this module only
parses arguments, shows progress and prints results. The library is imported when a
command runs, not when the app is built.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import typer

from semantic3d.cli import console as ui
from semantic3d.cli.cluster import open_cluster, scheduler_option, workers_option
from semantic3d.cli.console import fail, guarded, progress_bar, refuse_existing, threads_option

if TYPE_CHECKING:
    import numpy as np
    from rich.table import Table

    from semantic3d.io.conversion import ConvertedFile
    from semantic3d.io.formats import PointsSummary

#: ``semantic3d.io.chunks.DEFAULT_CHUNK_SIZE``, repeated so that building the app does not
#: import numpy (a test keeps the two equal).
DEFAULT_CHUNK_SIZE = 1 << 20
_LABELS_SUFFIX = ".labels"

_IN_HELP = "Input: .txt/.xyz (labels from the sibling .labels), .las, .laz, .ply or a cache folder."
_OVERWRITE_HELP = "Replace outputs that already exist (refused otherwise)."
_TO_SUFFIX = {
    "txt": ".txt",
    "xyz": ".xyz",
    "las": ".las",
    "laz": ".laz",
    "ply": ".ply",
    "cache": ".cache",
}
_ASCII_SUFFIXES = (".txt", ".xyz")
"""``semantic3d.io.formats.ASCII_SUFFIXES`` (not imported: building the app stays light)."""


def convert(
    paths: list[Path] = typer.Argument(
        ...,
        metavar="PATH",
        help="SOURCE DESTINATION, or with --out and --to any number of sources. "
        + _IN_HELP
        + " Output: .txt/.xyz (labels to OUT.labels), .las, .laz, .ply or NAME.cache.",
        show_default=False,
    ),
    out: Path | None = typer.Option(
        None,
        "--out",
        file_okay=False,
        help="Convert every SOURCE into this folder, as OUT/NAME.FORMAT (created if needed).",
    ),
    to: str | None = typer.Option(
        None, "--to", help=f"Output format with --out: {', '.join(_TO_SUFFIX)}."
    ),
    labels: Path | None = typer.Option(
        None,
        "--labels",
        exists=True,
        dir_okay=False,
        help="A .labels file with one label per input point (overrides the input's own; "
        "one source only).",
    ),
    chunk_size: int = typer.Option(
        DEFAULT_CHUNK_SIZE, "--chunk-size", min=1, help="Points per streamed chunk."
    ),
    crs: str | None = typer.Option(
        None,
        "--crs",
        help="LAS/LAZ output: the coordinate reference system, e.g. EPSG:2154 (any "
        "definition pyproj reads), written as a WKT record.",
    ),
    overwrite: bool = typer.Option(False, "--overwrite", help=_OVERWRITE_HELP),
    scheduler: str | None = scheduler_option(),
    workers: int | None = workers_option(),
    threads: int | None = threads_option(),
) -> None:
    """Convert point files between formats, streaming (constant memory).

    `convert SOURCE DESTINATION` converts one file; `convert SOURCE... --out DIR --to las`
    converts many, one Dask task per file with --scheduler or --workers (the same bytes
    as without). Each output is written under a hidden temporary name and renamed when
    complete: an error or Ctrl-C leaves no partial file and keeps what was at the
    destination. Existing outputs are refused (before any work) unless --overwrite is
    given; a missing output folder is created.
    """
    with guarded():
        jobs = _jobs(paths, out, to)
        if labels is not None and (len(jobs) > 1 or scheduler or workers):
            raise fail("--labels applies to one source converted in this process")
        outputs: list[Path] = []
        for source, destination in jobs:
            outputs += _check_job(source, destination, labels=labels, crs=crs)
        if crs is not None:
            from semantic3d.io.las import parse_crs

            parse_crs(crs)  # a bad one fails before any work
        refuse_existing(outputs, overwrite=overwrite)
        for folder in sorted({destination.parent for _, destination in jobs}):
            folder.mkdir(parents=True, exist_ok=True)
        with open_cluster(scheduler, workers) as cluster:
            if cluster is None:
                converted = [
                    _convert_here(source, destination, labels, chunk_size, crs)
                    for source, destination in jobs
                ]
            else:
                from semantic3d.scale.convert import convert_files_on_cluster

                with progress_bar() as bar:
                    task = bar.add_task(f"converting {len(jobs)} files", total=len(jobs))
                    converted = convert_files_on_cluster(
                        jobs,
                        cluster=cluster,
                        chunk_size=chunk_size,
                        crs=crs,
                        progress=lambda done, total: bar.update(task, completed=done),
                    )
        for file in converted:
            written = f"wrote {file.n_points:,} points to {file.destination}"
            if file.labelled and file.destination.suffix.lower() in _ASCII_SUFFIXES:
                written += f" and their labels to {file.destination.with_suffix(_LABELS_SUFFIX)}"
            elif file.labelled:
                written += " with labels"
            ui.console.print(written, highlight=False, soft_wrap=True)


def _jobs(paths: list[Path], out: Path | None, to: str | None) -> list[tuple[Path, Path]]:
    """``(source, destination)`` pairs of the two forms of the command."""
    if out is None:
        if to is not None:
            raise fail("--to applies with --out DIR")
        if len(paths) != 2:
            raise fail(
                f"expected SOURCE DESTINATION, or SOURCE... --out DIR --to FORMAT; "
                f"found {len(paths)} path{'s' if len(paths) != 1 else ''} and no --out"
            )
        jobs = [(paths[0], paths[1])]
    else:
        if to is None or to.lower().lstrip(".") not in _TO_SUFFIX:
            raise fail(f"--to: expected one of {', '.join(_TO_SUFFIX)}, found {to!r}")
        suffix = _TO_SUFFIX[to.lower().lstrip(".")]
        jobs = [(source, out / f"{source.stem}{suffix}") for source in paths]
        seen: dict[Path, Path] = {}
        for source, destination in jobs:
            if destination in seen:
                raise fail(f"{destination}: the output of both {seen[destination]} and {source}")
            seen[destination] = source
    for source, _ in jobs:
        if not source.exists():
            raise fail(f"{source}: expected a point file or cache folder, found nothing")
    return jobs


def _check_job(
    source: Path, destination: Path, *, labels: Path | None, crs: str | None
) -> list[Path]:
    """Fail on a job that cannot run; return the paths it would write."""
    from semantic3d.io.formats import (
        PointFormat,
        detect_format,
        estimate_point_count,
        sibling_labels_path,
    )

    in_format, out_format = detect_format(source), detect_format(destination)
    _require_extras(in_format, out_format)
    estimate_point_count(source)  # an unreadable header fails before any work
    if destination.exists() and destination.resolve() == source.resolve():
        raise fail(f"{destination}: output is the input file")
    if crs is not None and out_format not in (PointFormat.LAS, PointFormat.LAZ):
        raise fail(f"--crs applies to .las/.laz output, found {destination.name}")
    in_labels = labels
    if in_labels is None and in_format is PointFormat.ASCII:
        in_labels = sibling_labels_path(source)
    out_labels = destination.with_suffix(_LABELS_SUFFIX)
    if (
        out_format is PointFormat.ASCII
        and in_labels is not None
        and out_labels.resolve() == in_labels.resolve()
    ):
        raise fail(f"{out_labels}: output labels would overwrite the input labels")
    outputs = [destination]
    if out_format is PointFormat.ASCII and (
        in_labels is not None or in_format is not PointFormat.ASCII
    ):
        outputs.append(out_labels)
    if out_format is PointFormat.CACHE and destination.is_dir() and not any(destination.iterdir()):
        outputs.remove(destination)  # an empty folder holds nothing to lose
    return outputs


def _convert_here(
    source: Path, destination: Path, labels: Path | None, chunk_size: int, crs: str | None
) -> ConvertedFile:
    """One file in this process, with a progress bar of its points."""
    from semantic3d.io.conversion import convert_file

    with progress_bar() as bar:
        task = bar.add_task(f"{source.name} → {destination.name}", total=None)
        return convert_file(
            source,
            destination,
            labels_path=labels,
            chunk_size=chunk_size,
            crs=crs,
            progress=lambda done, total: bar.update(task, completed=done, total=total),
        )


def _require_extras(*formats: object) -> None:
    """Fail at once, in one line naming the extra, when a format's package is missing."""
    from semantic3d.core.errors import require
    from semantic3d.io.formats import PointFormat

    for kind in formats:
        if kind in (PointFormat.LAS, PointFormat.LAZ):
            require("laspy", "las")
            if kind is PointFormat.LAZ:
                require("lazrs", "las")
        elif kind is PointFormat.PLY:
            require("plyfile", "ply")


def info(
    path: Path = typer.Argument(..., exists=True, help=_IN_HELP),
    labels: Path | None = typer.Option(
        None, "--labels", exists=True, dir_okay=False, help="A .labels file to count instead."
    ),
    chunk_size: int = typer.Option(
        DEFAULT_CHUNK_SIZE, "--chunk-size", min=1, help="Points per streamed chunk."
    ),
    threads: int | None = threads_option(),
) -> None:
    """Show a point file's count, bounds, columns and class histogram (streaming)."""
    with guarded():
        from semantic3d.io.formats import (
            PointFormat,
            detect_format,
            estimate_point_count,
            sibling_labels_path,
            summarize_points,
        )

        _require_extras(detect_format(path))
        estimate = estimate_point_count(path)
        with progress_bar() as progress:
            task = progress.add_task(f"reading {path.name}", total=estimate.n_points)
            summary = summarize_points(
                path,
                chunk_size=chunk_size,
                labels_path=labels,
                progress=lambda done: progress.update(task, completed=done),
            )
            progress.update(task, total=summary.n_points, completed=summary.n_points)
        if labels is None and summary.format is PointFormat.ASCII:
            labels = sibling_labels_path(path)
        ui.console.print(_overview(summary, labels))
        if summary.label_counts is not None:
            ui.console.print(_histogram(summary.label_counts))


def _overview(summary: PointsSummary, labels: Path | None) -> Table:
    from rich.table import Table

    table = Table(title=str(summary.path), show_header=False, title_justify="left")
    table.add_column(style="bold")
    table.add_column()
    table.add_row("format", summary.format.value)
    table.add_row("points", f"{summary.n_points:,}")
    if summary.min_xyz is not None and summary.max_xyz is not None:
        for axis, name in enumerate("xyz"):
            low, high = summary.min_xyz[axis], summary.max_xyz[axis]
            table.add_row(
                f"{name} range (m)", f"{low:.3f} .. {high:.3f}  (extent {high - low:.3f})"
            )
    if summary.intensity_range is not None:
        table.add_row("intensity range", "{} .. {}".format(*summary.intensity_range))
    table.add_row("columns", "\n".join(summary.columns))
    if summary.label_counts is None:
        table.add_row("labels", "none")
    elif labels is not None:
        table.add_row("labels", str(labels))
    return table


def _histogram(counts: np.ndarray) -> Table:
    import numpy as np
    from rich.table import Table

    from semantic3d.core.classes import class_by_value

    total = int(counts.sum())
    table = Table(title="labels", title_justify="left")
    table.add_column("value", justify="right")
    table.add_column("class")
    table.add_column("points", justify="right")
    table.add_column("share", justify="right")
    for value in np.flatnonzero(counts):
        try:
            cls = class_by_value(int(value))
            name = f"[on {cls.hex_colour}]  [/] {cls.name}"
        except ValueError:
            name = "[dim]not a class[/]"
        count = int(counts[value])
        table.add_row(str(value), name, f"{count:,}", f"{100 * count / total:.2f} %")
    return table


def register(app: typer.Typer) -> None:
    """Add ``convert`` and ``info`` to ``app``."""
    app.command("convert")(convert)
    app.command("info")(info)
