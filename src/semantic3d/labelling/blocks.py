"""The scan's coordinates streamed in blocks for the operations: in order, or on threads.

Operations are compiled passes over the working points (:mod:`._op_kernels`); their input
is the cache's ``xyz.npy`` read block by block with positional reads (never a memory map,
whose pages would count as the server's memory), skipping blocks without an editable
working point.

:func:`map_blocks` runs a pass on numba's number of threads: each thread reads its blocks
into its own buffer and runs the compiled kernel, both without holding the GIL. Block
starts are multiples of 8, so the bit masks the passes write split between blocks at whole
bytes: the result does not depend on which thread ran which block, and equals the pass in
order. Progress is reported, and a cancel honoured, as the blocks complete in order.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, TypeVar

import numba
import numpy as np
from numpy.typing import NDArray

from semantic3d.labelling import _op_kernels as kernels

if TYPE_CHECKING:
    from semantic3d.labelling.session import LabelSession

__all__ = ["BLOCK_POINTS", "CoordinateReader", "block_threads", "iter_blocks", "map_blocks"]

BLOCK_POINTS = 1 << 20
"""Points read at a time when an operation streams the scan's coordinates (a multiple of 8)."""

T = TypeVar("T")


def block_threads() -> int:
    """Threads an operation's pass runs on: numba's (``NUMBA_NUM_THREADS``, the cores)."""
    return max(1, int(numba.get_num_threads()))


class CoordinateReader:
    """Positional reads of the scan's float64 coordinates (``with``: closes the file).

    :meth:`read` may be called from several threads at once.
    """

    def __init__(self, session: LabelSession) -> None:
        xyz = session.scan.xyz
        self.offset = int(xyz.offset) if isinstance(xyz, np.memmap) else 128
        self.path: Path = session.scan.path / "xyz.npy"
        self.fd = os.open(self.path, os.O_RDONLY)

    def read(self, start: int, rows: NDArray[np.float64]) -> None:
        """Fill ``rows`` (k, 3) with the coordinates of points ``start`` .. ``start + k``."""
        view = memoryview(rows.reshape(-1).view(np.uint8))  # type: ignore[arg-type]
        got = 0
        while got < view.nbytes:
            read = os.preadv(self.fd, [view[got:]], self.offset + start * 24 + got)
            if not read:
                raise OSError(f"{self.path}: unexpected end of file at point {start}")
            got += read

    def close(self) -> None:
        os.close(self.fd)

    def __enter__(self) -> CoordinateReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _has_active(session: LabelSession, editable: NDArray[np.bool_], start: int, stop: int) -> bool:
    return bool(kernels.any_active(session.labels, session.working, editable, start, stop))


def iter_blocks(
    session: LabelSession, *, active_only: bool = True
) -> Iterator[tuple[int, NDArray[np.float64]]]:
    """``(first index, float64 xyz block)`` in order, with progress and cancel.

    With ``active_only``, blocks holding no editable working point are skipped unread.
    The block is a reused buffer (valid until the next one).
    """
    size = BLOCK_POINTS
    buffer = np.empty((size, 3), np.float64)
    editable = session.editable_layers()
    with CoordinateReader(session) as reader:
        for start in range(0, session.n_points, size):
            stop = min(start + size, session.n_points)
            session.progress.update(start)
            if active_only and not _has_active(session, editable, start, stop):
                continue
            block = buffer[: stop - start]
            reader.read(start, block)
            yield start, block
    session.progress.update(session.n_points)


def map_blocks(
    session: LabelSession,
    work: Callable[[int, NDArray[np.float64]], T],
    *,
    active_only: bool = True,
    threads: int | None = None,
) -> list[T | None]:
    """``work(first index, xyz block)`` on every block, on ``threads`` threads.

    Returns the results in block order (``None`` for a block skipped: without an editable
    working point, when ``active_only``). ``work`` runs concurrently on different blocks:
    it may write only its block's part of shared outputs. Progress is reported and a
    cancel (an exception from ``session.progress.update``) honoured as blocks complete;
    blocks not yet started are then dropped and the exception raised once the running
    ones end.
    """
    size = BLOCK_POINTS
    n = session.n_points
    starts = list(range(0, n, size))
    editable = session.editable_layers()
    stopping = threading.Event()
    local = threading.local()
    reader = CoordinateReader(session)

    def run(start: int) -> T | None:
        if stopping.is_set():
            return None
        stop = min(start + size, n)
        if active_only and not _has_active(session, editable, start, stop):
            return None
        buffer = getattr(local, "buffer", None)
        if buffer is None:
            buffer = local.buffer = np.empty((size, 3), np.float64)
        block = buffer[: stop - start]
        reader.read(start, block)
        return work(start, block)

    count = max(1, min(threads or block_threads(), len(starts)))
    results: list[T | None] = []
    try:
        session.progress.update(0)
        with ThreadPoolExecutor(count, thread_name_prefix="labelling-pass") as pool:
            futures: list[Future[T | None]] = [pool.submit(run, start) for start in starts]
            try:
                for start, future in zip(starts, futures, strict=True):
                    results.append(future.result())
                    session.progress.update(min(start + size, n))
            except BaseException:
                stopping.set()
                for future in futures:
                    future.cancel()
                raise
    finally:
        reader.close()
    return results
