"""The error hierarchy.

Every error raised on bad input derives from :class:`Semantic3DError` and from the
matching built-in, so ``except ValueError`` keeps working for callers that do not know
this package. Messages say where, what was expected and what was found, e.g.
``scan.txt: line 1044: expected 7 columns (x y z intensity r g b), found 4``.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path


class Semantic3DError(Exception):
    """Root of every error this package raises on purpose."""


class DataFormatError(Semantic3DError, ValueError):
    """A file does not follow its format (wrong columns, non-numbers, values out of range)."""

    def __init__(self, message: str, *, path: str | None = None, line: int | None = None) -> None:
        where = ""
        if path is not None:
            where = f"{path}: "
            if line is not None:
                where += f"line {line}: "
        super().__init__(where + message)
        self.path = path
        self.line = line
        self.detail = message


class ConfigError(Semantic3DError, ValueError):
    """A configuration value or file is invalid; the message names the file, table and key
    (``model.toml: [forest] max_depth: expected a positive integer or "none", found -3``).
    """


class ShapeError(Semantic3DError, ValueError):
    """Arrays handed to a function have the wrong shape, length or dtype."""


class MissingExtraError(Semantic3DError, ImportError):
    """An optional dependency is not installed; the message names the extra to install.

    The message names the extra, not the module that failed to import (``sklearn.base``
    means nothing to a user who never asked for it); ``package`` keeps the module.
    """

    def __init__(self, package: str, extra: str) -> None:
        super().__init__(
            f"this feature needs the optional extra [{extra}]: pip install 'semantic3d[{extra}]'"
        )
        self.package = package
        self.extra = extra


class OutputExistsError(Semantic3DError, FileExistsError):
    """An output file exists and the caller did not ask to overwrite it.

    Made by :func:`refuse_existing_paths`, it keeps the first existing path and how many
    more there are, so the command line can name its own flag (``--overwrite``) where the
    library names its argument (``overwrite=True``).
    """

    def __init__(self, message: str, *, path: str | None = None, n_more: int = 0) -> None:
        super().__init__(message)
        self.path = path
        self.n_more = n_more


class GroundTruthOutputError(Semantic3DError, ValueError):
    """An output would replace the ground truth (``NAME.labels``) of a scan being read."""


class DownloadError(Semantic3DError, OSError):
    """A download or an archive extraction failed."""


class SubmissionError(Semantic3DError, ValueError):
    """A benchmark submission is invalid; ``problems`` lists every problem found at once."""

    def __init__(self, problems: Sequence[str], *, source: str | None = None) -> None:
        self.problems = tuple(problems)
        self.source = source
        head = f"{source}: " if source else ""
        count = len(self.problems)
        lines = "\n".join(f"  - {problem}" for problem in self.problems)
        noun = "problem" if count == 1 else "problems"
        super().__init__(f"{head}invalid submission, {count} {noun}:\n{lines}")


def refuse_existing_paths(paths: Sequence[Path], *, overwrite: bool) -> None:
    """Raise :class:`OutputExistsError` naming the first of ``paths`` that exists (a
    dangling link counts), unless ``overwrite``."""
    if overwrite:
        return
    existing = [path for path in paths if path.exists() or path.is_symlink()]
    if existing:
        n_more = len(existing) - 1
        more = f" (and {n_more} more)" if n_more else ""
        raise OutputExistsError(
            f"{existing[0]}: already exists{more}; pass overwrite=True to replace it",
            path=str(existing[0]),
            n_more=n_more,
        )


def require(package: str, extra: str) -> object:
    """Import ``package`` or raise :class:`MissingExtraError` naming the extra to install."""
    import importlib

    try:
        return importlib.import_module(package)
    except ImportError as exc:
        raise MissingExtraError(package, extra) from exc


def installed_version(distribution: str, extra: str) -> str:
    """The installed version of ``distribution`` (e.g. ``scikit-learn``), read from its
    metadata without importing it, or :class:`MissingExtraError` naming the extra."""
    from importlib import metadata

    try:
        return metadata.version(distribution)
    except metadata.PackageNotFoundError as exc:
        raise MissingExtraError(distribution, extra) from exc
