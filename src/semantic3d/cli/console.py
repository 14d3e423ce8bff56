"""Shared presentation for commands: the rich console, progress bars, error handling."""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import typer
from rich.console import Console
from rich.progress import (
    BarColumn,
    DownloadColumn,
    MofNCompleteColumn,
    Progress,
    ProgressColumn,
    TaskProgressColumn,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
    TransferSpeedColumn,
)

from semantic3d.core.errors import Semantic3DError

console = Console()
err_console = Console(stderr=True)


def fail(message: str) -> typer.Exit:
    """Print ``message`` as one red line on stderr; return the exit (code 2) to raise."""
    err_console.print(f"[bold red]error:[/] {message}", highlight=False, soft_wrap=True)
    return typer.Exit(code=2)


def run_guarded(app: Callable[..., object]) -> None:
    """Run ``app``, turning package errors into one red line and exit code 2."""
    try:
        app(standalone_mode=True)
    except Semantic3DError as exc:
        err_console.print(f"[bold red]error:[/] {exc}", highlight=False, soft_wrap=True)
        sys.exit(2)
    except KeyboardInterrupt:
        err_console.print("[yellow]interrupted[/]")
        sys.exit(130)


@contextmanager
def guarded() -> Iterator[None]:
    """Inside a command: turn package errors into one red line and exit code 2.

    Ctrl-C while a compiled (numba) kernel runs surfaces as ``SystemError: ... returned a
    result with an exception set`` caused by the interrupt; it is turned back into the
    ``KeyboardInterrupt`` it is, so the command ends like any other interrupted one.
    """
    try:
        yield
    except Semantic3DError as exc:
        raise fail(str(exc)) from None
    except SystemError as exc:
        if isinstance(exc.__cause__, KeyboardInterrupt):
            raise KeyboardInterrupt from None
        raise


def progress_bar(*, bytes_: bool = False) -> Progress:
    """A rich progress bar; ``bytes_`` shows sizes and transfer speed instead of counts."""
    columns: tuple[ProgressColumn, ...]
    if bytes_:
        columns = (
            TextColumn("{task.description}"),
            BarColumn(),
            DownloadColumn(),
            TransferSpeedColumn(),
            TimeRemainingColumn(),
        )
    else:
        columns = (
            TextColumn("{task.description}"),
            BarColumn(),
            MofNCompleteColumn(),
            TaskProgressColumn(),
            TimeElapsedColumn(),
            TimeRemainingColumn(),
        )
    return Progress(*columns, console=err_console, transient=False)
