"""``semantic3d download``: fetch the benchmark's scans into a folder."""

from __future__ import annotations

from enum import StrEnum
from pathlib import Path
from typing import TYPE_CHECKING

import typer

from semantic3d.cli import console as ui
from semantic3d.cli.console import escape, guarded, plural, progress_bar

if TYPE_CHECKING:
    from rich.progress import Progress, TaskID

    from semantic3d.datasets.download import DownloadProgress, DownloadReport
    from semantic3d.datasets.registry import Split
    from semantic3d.datasets.semantic3d import Semantic3D


class SplitChoice(StrEnum):
    """The ``--split`` values: one split of the registry (:class:`Split`, whose values a
    test keeps equal to these) or all of them."""

    TRAIN = "train"
    SEMANTIC_8 = "semantic-8"
    REDUCED_8 = "reduced-8"
    ALL = "all"

    def as_split(self) -> Split | None:
        """The registry split (``None`` for all)."""
        from semantic3d.datasets.registry import Split

        return None if self is SplitChoice.ALL else Split(self.value)


_LABEL_CHARS = 36


class _ProgressTasks:
    """Feeds download callbacks into a rich progress bar, one task per archive."""

    def __init__(self, bar: Progress) -> None:
        self.bar = bar
        self.tasks: dict[str, TaskID] = {}
        self.labels: dict[str, str] = {}

    def __call__(self, event: DownloadProgress) -> None:
        task = self.tasks.get(event.filename)
        if task is None:
            label = event.filename.removesuffix(".7z")
            label = label if len(label) <= _LABEL_CHARS else label[: _LABEL_CHARS - 1] + "…"
            task = self.bar.add_task(label, total=event.total_bytes)
            self.tasks[event.filename] = task
            self.labels[event.filename] = label
        label = self.labels[event.filename]
        if event.waiting is not None:  # the same line says why it waits, and how long
            self.bar.update(task, description=f"{label}: {escape(event.waiting)}")
            return
        self.bar.update(
            task, description=label, completed=event.done_bytes, total=event.total_bytes
        )


def _print_status(dataset: Semantic3D, split: Split | None) -> None:
    from rich.table import Table

    table = Table(title=f"semantic3D scans in {dataset.root}")
    for column in ("scan", "split", "points", "labels", "size"):
        table.add_column(column, justify="right" if column == "size" else "left")
    for files in dataset.scans(split):
        labels = "-" if files.labels_path is None else ("yes" if files.has_labels else "missing")
        table.add_row(
            files.scan.name,
            files.scan.split.value,
            "yes" if files.has_points else "missing",
            labels,
            f"{files.size_bytes / 1e9:.2f} GB" if files.size_bytes else "",
        )
    ui.console.print(table)
    missing = dataset.missing(split)
    ui.console.print(f"{len(dataset.scans(split)) - len(missing)} complete, {len(missing)} missing")


def _print_report(report: DownloadReport) -> None:
    ui.console.print(
        f"{plural(len(report.downloaded), 'scan')} downloaded, {len(report.skipped)} already "
        f"present, {len(report.failures)} failed -> {report.folder}"
    )


def download(
    split: SplitChoice = typer.Option(..., "--split", help="Which scans to fetch."),
    to: Path = typer.Option(..., "--to", help="Target folder (created if needed)."),
    base_url: str | None = typer.Option(
        None, "--base-url", help="Data root of a mirror (default: the semantic3d.net address)."
    ),
    retries: int = typer.Option(5, "--retries", min=0, help="Retries per archive."),
    keep_archives: bool = typer.Option(
        False, "--keep-archives", help="Keep the .7z files in <to>/.downloads."
    ),
    check: bool = typer.Option(
        False, "--check", help="Only list which scans are present; download nothing."
    ),
) -> None:
    """Download the benchmark's scans (resumable; files already present are skipped)."""
    with guarded():
        from semantic3d.core.errors import require
        from semantic3d.datasets.download import IncompleteDownloadError, download_scans
        from semantic3d.datasets.registry import scans
        from semantic3d.datasets.semantic3d import Semantic3D

        wanted = split.as_split()
        if check:
            _print_status(Semantic3D(to), wanted)
            return
        require("py7zr", "download")  # to extract what is downloaded: say so before
        with progress_bar(bytes_=True) as bar:
            try:
                report = download_scans(
                    scans(wanted),
                    to=to,
                    base_url=base_url,
                    progress=_ProgressTasks(bar),
                    retries=retries,
                    keep_archives=keep_archives,
                )
            except IncompleteDownloadError as exc:
                bar.stop()
                _print_report(exc.report)
                ui.err_console.print("[dim]run the command again to resume.[/]")
                raise
        _print_report(report)


def register(app: typer.Typer) -> None:
    """Add the ``download`` command to ``app``."""
    app.command("download")(download)
