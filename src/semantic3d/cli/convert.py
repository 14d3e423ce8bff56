"""``semantic3d convert`` and ``semantic3d info``: point files between formats, and what they hold.

Both stream in constant memory through :mod:`semantic3d.io.formats`; this module only
parses arguments, shows progress and prints results. The library is imported when a
command runs, not when the app is built.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import typer

from semantic3d.cli import console as ui
from semantic3d.cli.console import fail, guarded, progress_bar, refuse_existing

if TYPE_CHECKING:
    import numpy as np
    from rich.progress import Progress, TaskID
    from rich.table import Table

    from semantic3d.core.pointcloud import PointCloud
    from semantic3d.io.formats import PointsSummary

#: ``semantic3d.io.chunks.DEFAULT_CHUNK_SIZE``, repeated so that building the app does not
#: import numpy (a test keeps the two equal).
DEFAULT_CHUNK_SIZE = 1 << 20
_LABELS_SUFFIX = ".labels"

_IN_HELP = "Input: .txt/.xyz (labels from the sibling .labels), .las, .laz, .ply or a cache folder."
_OVERWRITE_HELP = "Replace outputs that already exist (refused otherwise)."


def convert(
    source: Path = typer.Argument(..., exists=True, help=_IN_HELP),
    destination: Path = typer.Argument(
        ..., help="Output: .txt/.xyz (labels to OUT.labels), .las, .laz, .ply or NAME.cache."
    ),
    labels: Path | None = typer.Option(
        None,
        "--labels",
        exists=True,
        dir_okay=False,
        help="A .labels file with one label per input point (overrides the input's own).",
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
) -> None:
    """Convert a point file between formats, streaming (constant memory).

    The output is written under a hidden temporary name and renamed when complete: an
    error or Ctrl-C leaves no partial file and keeps what was at the destination. An
    existing output is refused unless --overwrite is given; a missing output folder is
    created.
    """
    with guarded():
        from semantic3d.io.formats import (
            PointFormat,
            detect_format,
            estimate_point_count,
            iter_points,
            sibling_labels_path,
            write_points,
        )

        in_format, out_format = detect_format(source), detect_format(destination)
        _require_extras(in_format, out_format)
        if destination.exists() and destination.resolve() == source.resolve():
            raise fail(f"{destination}: output is the input file")
        parsed_crs = None
        if crs is not None:
            if out_format not in (PointFormat.LAS, PointFormat.LAZ):
                raise fail(f"--crs applies to .las/.laz output, found {destination.name}")
            from semantic3d.io.las import parse_crs

            parsed_crs = parse_crs(crs)  # a bad one fails before any work
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
        if (
            out_format is PointFormat.CACHE
            and destination.is_dir()
            and not any(destination.iterdir())
        ):
            outputs.remove(destination)  # an empty folder holds nothing to lose
        refuse_existing(outputs, overwrite=overwrite)
        estimate = estimate_point_count(source)
        chunks = iter_points(source, chunk_size=chunk_size, labels_path=labels)
        destination.parent.mkdir(parents=True, exist_ok=True)
        seen = _Seen()
        with progress_bar() as progress:
            task = progress.add_task(f"{source.name} → {destination.name}", total=estimate.n_points)
            n_points = write_points(destination, seen.count(chunks, progress, task), crs=parsed_crs)
            progress.update(task, total=n_points, completed=n_points)
        written = f"wrote {n_points:,} points to {destination}"
        if out_format is PointFormat.ASCII and seen.labels:
            written += f" and their labels to {out_labels}"
        elif seen.labels:
            written += " with labels"
        ui.console.print(written, highlight=False, soft_wrap=True)


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


class _Seen:
    """Counts chunks into a progress bar and remembers whether they carried labels."""

    def __init__(self) -> None:
        self.labels = False

    def count(
        self, chunks: Iterator[PointCloud], progress: Progress, task: TaskID
    ) -> Iterator[PointCloud]:
        for chunk in chunks:
            self.labels = self.labels or chunk.labels is not None
            yield chunk
            progress.update(task, advance=chunk.n_points)


def info(
    path: Path = typer.Argument(..., exists=True, help=_IN_HELP),
    labels: Path | None = typer.Option(
        None, "--labels", exists=True, dir_okay=False, help="A .labels file to count instead."
    ),
    chunk_size: int = typer.Option(
        DEFAULT_CHUNK_SIZE, "--chunk-size", min=1, help="Points per streamed chunk."
    ),
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
