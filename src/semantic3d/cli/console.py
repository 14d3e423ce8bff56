"""Shared presentation for commands: the rich consoles, progress bars, error handling.

Imported by every command module when the ``semantic3d`` app is built, so it stays light:
``console`` and ``err_console`` (rich consoles for stdout and stderr) are created on first
use, rich's progress bars when a bar is made, and nothing here imports numpy. Help is
plain text (``MARKUP_MODE``): typer's rich help imports a Markdown parser and Pygments,
which alone took longer than the 0.3 s budget of ``semantic3d --help``.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

import typer

from semantic3d.core.errors import MissingExtraError, OutputExistsError, Semantic3DError

if TYPE_CHECKING:
    from rich.console import Console
    from rich.progress import Progress

    console: Console
    err_console: Console

#: ``rich_markup_mode`` of every typer app of the command line: plain help, fast to show.
MARKUP_MODE = None


def __getattr__(name: str) -> Console:
    # The consoles, made on first use (importing rich.console costs ~40 ms at start-up).
    if name not in ("console", "err_console"):
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    from rich.console import Console

    made = Console(stderr=name == "err_console")
    globals()[name] = made
    return made


def escape(text: str) -> str:
    """``text`` with rich markup escaped, so that ``[las]`` prints as written."""
    from rich.markup import escape as rich_escape

    return rich_escape(text)


#: The extra that installs each optional top-level module, for an import that fails
#: outside :func:`semantic3d.core.errors.require` (the message then still names it).
EXTRA_BY_MODULE = {
    "laspy": "las",
    "lazrs": "las",
    "pyproj": "las",
    "plyfile": "ply",
    "py7zr": "download",
    "matplotlib": "viz",
    "scipy": "sim",
    "sklearn": "ml",
    "joblib": "ml",
    "pgeof": "ml",
    **dict.fromkeys(
        (
            "fastapi",
            "starlette",
            "uvicorn",
            "sqlalchemy",
            "alembic",
            "jinja2",
            "multipart",
            "argon2",
            "itsdangerous",
            "pydantic_settings",
            "httpx",
        ),
        "server",
    ),
}


THREADS_HELP = (
    "Threads to compute with (default: every core, or NUMBA_NUM_THREADS / OMP_NUM_THREADS "
    "when set). Results are the same for any number."
)


def threads_option() -> Any:
    """The ``--threads N`` option: caps the command's compute threads while it runs
    (:func:`semantic3d.core.threads.set_thread_limit`, applied as the option is parsed, so
    before the command imports numba; the previous cap is back when the command ends).
    A command with it computes: the C allocator keeps freed memory for reuse from then on
    (:func:`semantic3d.core.allocator.keep_freed_memory`)."""
    return typer.Option(None, "--threads", min=1, help=THREADS_HELP, callback=_use_threads)


def _use_threads(context: typer.Context, value: int | None) -> int | None:
    from semantic3d.core.allocator import keep_freed_memory

    keep_freed_memory()  # a compute command: freed memory kept for the next tile's arrays
    if value is not None:
        from semantic3d.core import threads

        previous = threads.current_thread_limit()
        threads.set_thread_limit(value)
        context.call_on_close(lambda: threads.set_thread_limit(previous))
    return value


def print_error(message: str) -> None:
    """``message`` as one red line on stderr, printed literally (no rich markup)."""
    _err_console().print(f"[bold red]error:[/] {escape(message)}", highlight=False, soft_wrap=True)


def fail(message: str) -> typer.Exit:
    """Print ``message`` as one red line on stderr; return the exit (code 2) to raise."""
    print_error(message)
    return typer.Exit(code=2)


def plural(count: int, noun: str, plural_noun: str | None = None) -> str:
    """``"1 scan"``, ``"2 scans"``.

    >>> plural(1, "scan"), plural(3, "scan"), plural(0, "entry", "entries")
    ('1 scan', '3 scans', '0 entries')
    """
    return f"{count:,} {noun if count == 1 else (plural_noun or noun + 's')}"


def _error_message(exc: BaseException) -> str | None:
    """The one-line message for an error that is the user's environment, not a bug."""
    if isinstance(exc, OutputExistsError) and exc.path is not None:
        more = f" (and {plural(exc.n_more, 'other output')})" if exc.n_more else ""
        return f"{exc.path}: already exists{more}; pass --overwrite to replace it"
    if isinstance(exc, Semantic3DError):
        return str(exc)
    if isinstance(exc, ModuleNotFoundError) and exc.name:
        extra = EXTRA_BY_MODULE.get(exc.name.partition(".")[0])
        if extra is not None:
            return str(MissingExtraError(exc.name, extra))
        return None
    if isinstance(exc, OSError) and exc.strerror:
        where = f"{exc.filename}: " if exc.filename else ""
        return f"{where}{exc.strerror[:1].lower()}{exc.strerror[1:]}"
    return None


def run_guarded(app: Callable[..., object]) -> None:
    """Run ``app``, turning package errors and command-line mistakes into one red line and
    exit code 2 (a missing path is ``error: semantic3d info: invalid value for 'path': path
    'x.txt' does not exist (see semantic3d info --help)``, not click's usage block)."""
    try:
        result = app(standalone_mode=False)
    except (KeyboardInterrupt, typer.Abort):
        result = 130
    except (Semantic3DError, ImportError, OSError) as exc:
        message = _error_message(exc)
        if message is None:
            raise
        print_error(message)
        sys.exit(2)
    except Exception as exc:
        if not isinstance(exc, _click_class("ClickException")):
            raise
        if type(exc).__name__ == "NoArgsIsHelpError":  # a bare command group: its help
            exc.show()  # type: ignore[attr-defined]
        else:
            print_error(_usage_message(exc))
        sys.exit(exc.exit_code)  # type: ignore[attr-defined]
    if result == 130:  # Ctrl-C (typer turns it into this exit code)
        _err_console().print("[yellow]interrupted[/]")
    sys.exit(result if isinstance(result, int) else 0)


def _click_class(name: str) -> type:
    """click's ``ClickException`` or ``UsageError``, whichever click typer runs on (a
    vendored copy in recent releases), found among the bases of ``typer.BadParameter``."""
    return next(base for base in typer.BadParameter.__mro__ if base.__name__ == name)


def _usage_message(exc: Exception) -> str:
    """One line for a command-line mistake: the command, the message, where help is."""
    message = exc.format_message().rstrip(".")  # type: ignore[attr-defined]
    message = message[:1].lower() + message[1:]
    context = getattr(exc, "ctx", None)
    if isinstance(exc, _click_class("UsageError")) and context is not None:
        return f"{context.command_path}: {message} (see {context.command_path} --help)"
    return message


@contextmanager
def guarded() -> Iterator[None]:
    """Inside a command: turn package errors into one red line and exit code 2.

    Also turned into one line: a missing optional package (the message names the extra
    to install) and an operating-system error on a file (``out/x.las: permission
    denied``). Ctrl-C while a compiled (numba) kernel runs surfaces as ``SystemError: ...
    returned a result with an exception set`` caused by the interrupt; it is turned back
    into the ``KeyboardInterrupt`` it is, so the command ends like any other interrupted
    one.
    """
    try:
        yield
    except (Semantic3DError, ImportError, OSError) as exc:
        message = _error_message(exc)
        if message is None:
            raise
        raise fail(message) from None
    except SystemError as exc:
        if isinstance(exc.__cause__, KeyboardInterrupt):
            raise KeyboardInterrupt from None
        raise


def refuse_existing(paths: Iterable[Path], *, overwrite: bool) -> None:
    """Exit with one red line when an output exists and ``--overwrite`` was not given.

    Every command checks its outputs before it starts working, so a long run never ends
    by refusing to write (writers stage their output under a temporary name, so an
    interrupted run still leaves the old file in place).
    """
    if overwrite:
        return
    existing = [path for path in paths if path.exists() or path.is_symlink()]
    if not existing:
        return
    more = f" (and {plural(len(existing) - 1, 'other output')})" if len(existing) > 1 else ""
    raise fail(f"{existing[0]}: already exists{more}; pass --overwrite to replace it")


def write_atomically(path: Path, write: Callable[[Path], object]) -> None:
    """``write(temp)`` to a hidden sibling of ``path``, then rename it into place.

    On any error (Ctrl-C included) the sibling is removed and ``path`` is left as it was.
    """
    import uuid

    temp = path.with_name(f".{path.stem}.{uuid.uuid4().hex[:8]}.partial{path.suffix}")
    try:
        write(temp)
        temp.replace(path)
    except BaseException:
        temp.unlink(missing_ok=True)
        raise


def progress_bar(*, bytes_: bool = False) -> Progress:
    """A rich progress bar; ``bytes_`` shows sizes and transfer speed instead of counts."""
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
    return Progress(*columns, console=_err_console(), transient=False)


def _err_console() -> Console:
    made = globals().get("err_console")
    return made if made is not None else __getattr__("err_console")
