"""A label per point of a scan, filled in any order, read back in scan order, in bounded memory."""

from __future__ import annotations

import contextlib
import mmap
import os
from collections.abc import Iterator
from pathlib import Path
from types import TracebackType

import numpy as np
from numpy.typing import NDArray

__all__ = ["LabelBuffer"]


class LabelBuffer:
    """A uint8 label per point in a memory-mapped scratch file.

    Tiles label their points in any order (:meth:`put`); :meth:`iter_chunks` then reads
    them in scan order for the ``.labels`` writer. Resident pages are dropped as blocks
    are written and read, so memory does not grow with the scan (one byte a point on disk).
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._file = self.path.open("w+b")
        self._map: mmap.mmap | None = None
        self.n_points = 0

    def __enter__(self) -> LabelBuffer:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.close()

    def _ensure(self, n_points: int) -> NDArray[np.uint8]:
        if self._map is None:
            self.n_points = n_points
            os.ftruncate(self._file.fileno(), max(n_points, 1))
            self._map = mmap.mmap(self._file.fileno(), max(n_points, 1))
        return np.frombuffer(self._map, np.uint8, count=self.n_points)

    def put(self, indices: NDArray[np.int64], labels: NDArray[np.uint8], n_points: int) -> None:
        """Set the labels of points ``indices`` of a scan of ``n_points`` points."""
        view = self._ensure(n_points)
        view[indices] = labels
        del view
        self._release()

    def iter_chunks(self, chunk_size: int) -> Iterator[NDArray[np.uint8]]:
        """The labels in scan order, ``chunk_size`` at a time (copies)."""
        view = self._ensure(0)
        for begin in range(0, self.n_points, chunk_size):
            yield view[begin : begin + chunk_size].copy()
            self._release()
        del view

    def _release(self) -> None:
        if self._map is not None:
            self._map.flush()
            self._map.madvise(mmap.MADV_DONTNEED)

    def close(self) -> None:
        """Unmap and close the scratch file (the caller removes its folder)."""
        if self._map is not None:
            with contextlib.suppress(BufferError):  # a live view: the file goes with the folder
                self._map.close()
        self._file.close()
