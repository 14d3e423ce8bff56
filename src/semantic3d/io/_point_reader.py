"""The streaming driver of the ASCII point parser (:mod:`semantic3d.io._ascii_kernels`).

A regular file is memory-mapped (no copy out of the page cache), advised sequential, and
parsed in windows of whole lines straight into the output arrays of the current batch;
pages behind the cursor are dropped from the mapping so resident memory stays flat
whatever the file size. Anything that cannot be mapped (a pipe) is read in blocks of
whole lines instead. Batches hold a whole number of chunks, so chunks are slices of
them: exact ``chunk_size`` without joining pieces.

Python runs once per window (megabytes), never per line: it only resolves what the
kernel defers (tokens needing the general float algorithm) and turns the first problem
into a :class:`~semantic3d.core.errors.DataFormatError` naming file, line, expected and
found.
"""

from __future__ import annotations

import mmap
from collections.abc import Generator, Iterator
from contextlib import suppress
from pathlib import Path

import numba
import numpy as np

from semantic3d.core.pointcloud import PointCloud
from semantic3d.io import _ascii_kernels as kernels
from semantic3d.io import _point_text as codes
from semantic3d.io._point_text import MAX_LINE_BYTES
from semantic3d.io._point_text import line_at as _line_at
from semantic3d.io._point_text import long_line_error as _long_line_error
from semantic3d.io._point_text import point_error as _point_error
from semantic3d.io.chunks import iter_line_blocks

MIN_LINE_BYTES = 14
"""``0 0 0 0 0 0 0\\n``: bounds the number of rows a byte range can hold."""
MIN_BATCH_ROWS = 1 << 16
_SEGMENT_BYTES = 1 << 16  # the least worth a thread
_SLOW_CAPACITY = 4096  # deferred tokens per segment before it pauses for conversion
_TOKEN_WIDTH = 64
_RELEASE_BYTES = 16 << 20
_Region = tuple[np.ndarray, int, int, int, int]
"""A buffer, the range of whole lines to parse in it, how far it may be read, and the
(page-aligned) offset before which its pages may be dropped from its mapping (0: none)."""


def iter_point_batches(path: Path, chunk_size: int, window_bytes: int) -> Iterator[PointCloud]:
    """Chunks of exactly ``chunk_size`` points of ``path`` (the last may be shorter)."""
    reader = _Reader(path, chunk_size, window_bytes)
    size = path.stat().st_size
    with path.open("rb", buffering=0) as stream:
        mapped = _map(stream, size)
        if mapped is None:
            regions = _block_regions(path, window_bytes)
        else:
            step = max(_RELEASE_BYTES, 2 * reader.window_bytes)
            regions = _mapped_regions(path, mapped, size, step)
        try:
            yield from reader.run(regions, size if mapped is not None else None)
        finally:
            regions.close()
            if mapped is not None:
                with suppress(BufferError):
                    mapped.close()


class _Batch:
    def __init__(self, capacity: int) -> None:
        self.xyz = np.empty((capacity, 3), np.float64)
        self.intensity = np.empty(capacity, np.int32)
        self.rgb = np.empty((capacity, 3), np.uint8)
        self.capacity = capacity
        self.filled = 0

    def chunks(self, chunk_size: int) -> Iterator[PointCloud]:
        for start in range(0, self.filled, chunk_size):
            stop = min(start + chunk_size, self.filled)
            yield PointCloud(self.xyz[start:stop], self.intensity[start:stop], self.rgb[start:stop])


class _Reader:
    def __init__(self, path: Path, chunk_size: int, window_bytes: int) -> None:
        self.path = path
        self.chunk_size = chunk_size
        # more threads, longer windows: the Python between two windows stays a small share
        self.window_bytes = max(int(window_bytes), 1) * max(1, numba.get_num_threads() // 4)
        self.batch_rows = chunk_size * max(1, -(-MIN_BATCH_ROWS // chunk_size))
        # several segments per thread: equal bytes are not equal work on a loaded machine
        self.max_segments = max(1, numba.get_num_threads() * 16)
        self.slow = np.empty((self.max_segments, _SLOW_CAPACITY, 4), np.int64)
        self.state = np.zeros((self.max_segments, kernels.STATE_SIZE), np.int64)
        self.lines_before = 0  # lines of earlier batches
        self.bytes_left: int | None = None
        self.dropped = 0  # the mapping's pages before this offset are dropped

    def run(self, regions: Iterator[_Region], size: int | None) -> Iterator[PointCloud]:
        self.bytes_left = size
        batch = self._new_batch()
        for buf, start, stop, readable, droppable in regions:
            pos = start
            while pos < stop:
                if batch.filled == batch.capacity:
                    yield from batch.chunks(self.chunk_size)
                    self.lines_before += batch.filled
                    batch = self._new_batch()
                pos = self._parse_window(buf, readable, pos, stop, batch, droppable)
        if batch.filled:
            yield from batch.chunks(self.chunk_size)

    def consumed(self, n_bytes: int) -> None:
        if self.bytes_left is not None:
            self.bytes_left -= n_bytes

    def _new_batch(self) -> _Batch:
        capacity = self.batch_rows
        if self.bytes_left is not None:  # a small file (or its end) needs a small batch
            capacity = min(capacity, (self.bytes_left + 1) // MIN_LINE_BYTES + 1)
        return _Batch(capacity)

    def _parse_window(
        self, buf: np.ndarray, readable: int, pos: int, stop: int, batch: _Batch, droppable: int
    ) -> int:
        window_stop = kernels.window_end(buf, pos, pos + self.window_bytes, stop, MAX_LINE_BYTES)
        if window_stop < 0:
            raise _long_line_error(self.path)
        room = batch.capacity - batch.filled
        n_segments = int(max(1, min(self.max_segments, (window_stop - pos) // _SEGMENT_BYTES)))
        drop_start = self.dropped
        self.dropped = max(self.dropped, droppable)
        n_lines, n_segments, window_stop = kernels.parse_window(
            buf,
            readable,
            pos,
            window_stop,
            n_segments,
            batch.filled,
            room,
            batch.xyz,
            batch.intensity,
            batch.rgb,
            self.slow,
            self.state,
            numba.get_num_threads(),
            drop_start,
            self.dropped,
        )
        state = self.state[:n_segments]
        if state[:, kernels.STATE_STATUS].any() or state[:, kernels.STATE_SLOW].any():
            for segment in range(n_segments):
                self._resolve(buf, readable, segment, batch)
        batch.filled += int(n_lines)
        self.consumed(window_stop - pos)
        return int(window_stop)

    def _resolve(self, buf: np.ndarray, readable: int, segment: int, batch: _Batch) -> None:
        """Convert a segment's deferred tokens, resume it when it paused, raise its problem."""
        status, pos, row, n_slow, end = (int(v) for v in self.state[segment])
        slow = self.slow[segment]
        while True:
            if n_slow:
                self._convert(buf, slow[:n_slow], batch)
            if status == codes.SLOW_FULL:
                status, pos, row, n_slow = kernels.parse_segment(
                    buf, readable, pos, end, row, batch.xyz, batch.intensity, batch.rgb, slow
                )
                continue
            if status != codes.OK:
                raise _point_error(self.path, _line_at(buf, pos), status, self._line(row))
            return

    def _convert(self, buf: np.ndarray, slow: np.ndarray, batch: _Batch) -> None:
        """Exact values of deferred tokens (CPython's correctly rounded ``dtoa``, via numpy)."""
        table = kernels.gather_tokens(buf, slow, _TOKEN_WIDTH)
        values = table.view(f"S{_TOKEN_WIDTH}").ravel().astype(np.float64)
        lengths = slow[:, kernels.SLOW_STOP] - slow[:, kernels.SLOW_START]
        for i in np.flatnonzero(lengths > _TOKEN_WIDTH):
            start, stop = int(slow[i, kernels.SLOW_START]), int(slow[i, kernels.SLOW_STOP])
            values[i] = float(bytes(buf[start:stop]))
        rows, columns = slow[:, kernels.SLOW_ROW], slow[:, kernels.SLOW_COLUMN]
        problem = np.where(np.isfinite(values), codes.OK, codes.NON_FINITE)
        integer = columns >= 3
        with np.errstate(invalid="ignore"):
            fraction = integer & (problem == codes.OK) & (values != np.floor(values))
            problem[fraction] = codes.NOT_INTEGER
            low = np.where(columns == 3, -2147483648.0, 0.0)
            high = np.where(columns == 3, 2147483647.0, 255.0)
            outside = integer & (problem == codes.OK) & ((values < low) | (values > high))
        problem[outside] = codes.OUT_OF_RANGE
        bad = np.flatnonzero(problem)
        if bad.size:
            first = int(bad[np.argmin(rows[bad])])
            raise _point_error(
                self.path,
                _line_at(buf, int(slow[first, kernels.SLOW_START])),
                int(problem[first]),
                self._line(int(rows[first])),
            )
        coordinate = ~integer
        batch.xyz[rows[coordinate], columns[coordinate]] = values[coordinate]
        intensity = columns == 3
        batch.intensity[rows[intensity]] = values[intensity].astype(np.int32)
        colour = columns > 3
        batch.rgb[rows[colour], columns[colour] - 4] = values[colour].astype(np.uint8)

    def _line(self, row: int) -> int:
        return self.lines_before + row + 1


def _map(stream: object, size: int) -> mmap.mmap | None:
    """A read-only map of the file, or None when it cannot be mapped (a pipe, size 0)."""
    if size == 0:
        return None
    try:
        mapped = mmap.mmap(stream.fileno(), 0, access=mmap.ACCESS_READ)  # type: ignore[attr-defined]
    except (OSError, ValueError):
        return None
    with suppress(OSError, AttributeError):
        mapped.madvise(mmap.MADV_SEQUENTIAL)
    return mapped


def _mapped_regions(
    path: Path, mapped: mmap.mmap, size: int, step: int
) -> Generator[_Region, None, None]:
    """The mapped file up to its last newline, then (padded copy) a last line without one."""
    body_end = mapped.rfind(b"\n") + 1
    if size - body_end > MAX_LINE_BYTES:
        raise _long_line_error(path)
    buf = np.frombuffer(mapped, np.uint8)
    try:
        if body_end:
            yield from _released(mapped, buf, body_end, size, step)
        if body_end < size:
            tail = mapped[body_end:size] + b"\n" + bytes(kernels.FAST_MARGIN)
            padded = np.frombuffer(tail, np.uint8)
            yield padded, 0, size - body_end + 1, padded.size, 0
    finally:
        del buf


def _released(
    mapped: mmap.mmap, buf: np.ndarray, body_end: int, size: int, step: int
) -> Iterator[_Region]:
    """Yield the body in steps, each with the offset before which the pages behind the
    cursor may be dropped from the mapping (the parser's threads drop them:
    :func:`~semantic3d.io._ascii_kernels.parse_window`).

    Dropped pages stay in the page cache; they only stop counting as this process's
    resident memory (a 17 GB scan would otherwise look like a 17 GB process).
    """
    behind = 0  # the previous steps' whole pages
    start = 0
    while start < body_end:
        stop = min(start + step, body_end)
        if stop < body_end:  # whole lines only: extend to the next newline
            stop = mapped.find(b"\n", stop - 1) + 1
        ahead = stop - stop % mmap.PAGESIZE
        with suppress(OSError, ValueError, AttributeError):  # no madvise: nothing to advise
            mapped.madvise(mmap.MADV_WILLNEED, ahead, min(step, size - ahead))
        yield buf, start, stop, size, behind
        behind = stop - stop % mmap.PAGESIZE
        start = stop


def _block_regions(path: Path, block_bytes: int) -> Generator[_Region, None, None]:
    for block in iter_line_blocks(path, block_bytes=max(block_bytes, 1 << 16)):
        view = block.view()
        view.flags.writeable = False
        yield view, 0, view.size, view.size, 0
