"""The ``semantic3d`` typer application.

Each command module exposes ``register(app)``; this module only wires them together.
Commands parse arguments, call the library and present the result. Errors derived from
:class:`~semantic3d.core.errors.Semantic3DError` print one red line and exit with code 2.
"""

from __future__ import annotations

import importlib
import logging
import os

import typer

from semantic3d import __version__
from semantic3d.cli.console import MARKUP_MODE, run_guarded

app = typer.Typer(
    rich_markup_mode=MARKUP_MODE,
    name="semantic3d",
    help="Semantic classification of huge terrestrial laser scans (semantic3D.net).",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)

# Command modules, in the order their commands appear in --help.
_COMMAND_MODULES = (
    "semantic3d.cli.demo",
    "semantic3d.cli.convert",
    "semantic3d.cli.download",
    "semantic3d.cli.simulate",
    "semantic3d.cli.cubemap",
    "semantic3d.cli.evaluate",
    "semantic3d.cli.baseline",
    "semantic3d.cli.label",
    "semantic3d.cli.server",
)


def _version(value: bool) -> None:
    if value:
        typer.echo(f"semantic3d {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Log progress details."),
    version: bool = typer.Option(
        False, "--version", callback=_version, is_eager=True, help="Print the version."
    ),
) -> None:
    logging.basicConfig(
        level=logging.INFO if verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )
    if not verbose:
        _quiet_other_libraries()


def _quiet_other_libraries() -> None:
    """Without ``-v`` only this package logs: a library's own error lines (laspy's on a
    truncated LAZ file) would come before, and say less than, the one line the command
    prints; Dask's scheduler and workers (their own processes too, through the
    environment they inherit) log warnings and errors only."""
    for handler in logging.getLogger().handlers:
        handler.addFilter(_this_package_or_critical)
    os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", "warning")


def _this_package_or_critical(record: logging.LogRecord) -> bool:
    return record.name.partition(".")[0] == "semantic3d" or record.levelno >= logging.CRITICAL


for _module_name in _COMMAND_MODULES:
    importlib.import_module(_module_name).register(app)


def main() -> None:
    """Console-script entry point."""
    run_guarded(app)


if __name__ == "__main__":
    main()
