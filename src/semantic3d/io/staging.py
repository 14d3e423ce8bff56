"""Staged output: files written under temporary names, renamed into place when complete.

Every writer of this package streams its output, so a failure, a Ctrl-C or a crash half
way would otherwise leave a truncated file under the name the user asked for (and destroy
the file that was there). Writers open :attr:`StagedPath.temp` instead, a hidden sibling
in the same folder (same filesystem, so the final :meth:`~StagedPath.commit` is one atomic
rename), and remove it on any exception, ``KeyboardInterrupt`` included. The temporary
name keeps the final suffix, so format detection and readers work on it unchanged.

:class:`StagedWriter` is the protocol every point writer follows on top of that
(``write`` chunks, ``close`` completes, ``abort`` discards; ``with`` picks one), and
:func:`write_chunks` the loop every ``write_*`` function runs.

>>> staged = StagedPath(Path("out/scan.laz"))
>>> staged.temp.parent == Path("out") and staged.temp.suffix == ".laz"
True
>>> staged.temp.name.startswith(".scan.") and ".partial" in staged.temp.name
True
"""

from __future__ import annotations

import uuid
from abc import ABC, abstractmethod
from collections.abc import Iterable
from pathlib import Path
from types import TracebackType
from typing import Self, TypeVar

from semantic3d.core.errors import DataFormatError
from semantic3d.core.pointcloud import PointCloud


class StagedPath:
    """A final path and the temporary sibling written in its place until :meth:`commit`."""

    def __init__(self, final: str | Path) -> None:
        self.final = Path(final)
        tag = uuid.uuid4().hex[:8]
        self.temp = self.final.with_name(f".{self.final.stem}.{tag}.partial{self.final.suffix}")

    def commit(self) -> None:
        """Rename the temporary file to the final name (replacing what was there)."""
        self.temp.replace(self.final)

    def discard(self) -> None:
        """Remove the temporary file, if any; the final name is left untouched."""
        self.temp.unlink(missing_ok=True)

    def __repr__(self) -> str:
        return f"StagedPath({str(self.final)!r})"


class StagedWriter(ABC):
    """A streaming point writer: :meth:`write` chunks, then :meth:`close` or :meth:`abort`.

    As a context manager it closes when the block succeeds and aborts on any exception
    (Ctrl-C included), and aborts too when closing fails: the final path then holds
    either the complete output or what was there before, never a partial file.
    """

    path: Path
    n_points: int

    @abstractmethod
    def write(self, cloud: PointCloud) -> None:
        """Append ``cloud``."""

    @abstractmethod
    def close(self) -> None:
        """Finish the output and move it to its final path."""

    @abstractmethod
    def abort(self) -> None:
        """Drop what was written; the final path is left as it was."""

    def check_labels(self, cloud: PointCloud, expected: bool) -> None:
        """Raise unless ``cloud`` carries labels exactly when the first chunk did."""
        found = cloud.labels is not None
        if found != expected:
            raise DataFormatError(
                f"expected every chunk {'with' if expected else 'without'} labels (as the "
                f"first), found chunk at point #{self.n_points} {'with' if found else 'without'}",
                path=str(self.path),
            )

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        if exc_type is not None:
            self.abort()
            return
        try:
            self.close()
        except BaseException:
            self.abort()
            raise


W = TypeVar("W", bound=StagedWriter)


def write_chunks(writer: W, chunks: Iterable[PointCloud]) -> int:
    """Write every chunk with ``writer`` and close it (abort on failure); return the count."""
    with writer:
        for chunk in chunks:
            writer.write(chunk)
    return writer.n_points
