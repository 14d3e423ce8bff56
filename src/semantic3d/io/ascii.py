"""Semantic3D ASCII point files: ``x y z intensity r g b``, one point per line.

The benchmark's scans hold up to ~500 M lines (~17 GB); everything here streams in
blocks of whole lines and keeps memory constant. Accepted: spaces or tabs between
columns, blanks at line ends, CRLF, a missing final newline, signed integer
intensities (``-1515``). Rejected with file, line, expected and found: a line without
exactly 7 columns, a token that is not a number, a fractional intensity or colour,
colours outside 0..255.

Files up to 256 KiB are parsed in Python (:mod:`semantic3d.io._point_text`), larger ones
by compiled kernels; both accept and reject the same text with the same messages.

Labels live beside the points in a ``.labels`` file (:mod:`semantic3d.io.labels`); pass
``labels_path`` to read or write them together, chunk for chunk.
"""

from __future__ import annotations

import stat
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import BinaryIO

import numpy as np

from semantic3d.core.errors import DataFormatError
from semantic3d.core.pointcloud import PointCloud
from semantic3d.io._point_text import COLUMNS, SMALL_FILE_BYTES, iter_small_points
from semantic3d.io.chunks import DEFAULT_CHUNK_SIZE, validate_chunk_size
from semantic3d.io.labels import attach_labels
from semantic3d.io.staging import StagedPath, StagedWriter, write_chunks

__all__ = [
    "COLUMNS",
    "AsciiPointWriter",
    "iter_ascii_points",
    "open_ascii_writer",
    "read_ascii_points",
    "write_ascii_points",
]

DEFAULT_WINDOW_BYTES = 8 << 20
"""Bytes of text parsed per call of the compiled kernel (split over all cores)."""
MAX_DECIMALS = 9
_FORMAT_BATCH = 1 << 17
_NO_LABELS = np.empty(0, np.uint8)


def iter_ascii_points(
    path: str | Path,
    *,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
    labels_path: str | Path | None = None,
    block_bytes: int = DEFAULT_WINDOW_BYTES,
) -> Iterator[PointCloud]:
    """Stream the points of ``path`` in chunks of exactly ``chunk_size`` (the last may be shorter).

    With ``labels_path``, each chunk carries its labels; a label file with a different
    number of lines raises :class:`~semantic3d.core.errors.DataFormatError`.
    ``block_bytes`` is how much text one call of the compiled parser takes (a tuning
    knob; results do not depend on it). Memory stays bounded by the chunks and one window
    whatever the file size.
    """
    chunk_size = validate_chunk_size(chunk_size)
    path = Path(path)
    clouds = _iter_ascii_chunks(path, chunk_size, block_bytes)
    if labels_path is None:
        return clouds
    return attach_labels(path, clouds, Path(labels_path), chunk_size=chunk_size)


def _iter_ascii_chunks(path: Path, chunk_size: int, block_bytes: int) -> Iterator[PointCloud]:
    """Small regular files through the Python parser, the rest through the kernels."""
    status = path.stat()
    if stat.S_ISREG(status.st_mode) and status.st_size <= SMALL_FILE_BYTES:
        with path.open("rb") as stream:
            data = stream.read(SMALL_FILE_BYTES + 1)
        if len(data) <= SMALL_FILE_BYTES:  # else it grew meanwhile
            yield from iter_small_points(path, data, chunk_size)
            return
    from semantic3d.io._point_reader import iter_point_batches

    yield from iter_point_batches(path, chunk_size, block_bytes)


def read_ascii_points(path: str | Path, *, labels_path: str | Path | None = None) -> PointCloud:
    """The whole file as one :class:`PointCloud` (a thin wrapper over :func:`iter_ascii_points`)."""
    chunks = list(iter_ascii_points(path, labels_path=labels_path))
    if not chunks:
        return PointCloud.empty(with_labels=labels_path is not None)
    return chunks[0] if len(chunks) == 1 else PointCloud.concatenate(chunks)


class AsciiPointWriter(StagedWriter):
    """Writes point chunks (and their labels, when a labels path is given) as they come.

    Output bytes depend only on the arrays and ``decimals``: the same data always gives
    the same file. Coordinates are rounded to ``decimals`` places (3: millimetres, as the
    benchmark's files). Both files are written under temporary names and renamed into
    place by :meth:`close` (:class:`~semantic3d.io.staging.StagedPath`); on an exception
    inside the ``with`` block (Ctrl-C included) they are removed and the final names are
    left as they were.
    """

    def __init__(
        self, path: str | Path, *, labels_path: str | Path | None = None, decimals: int = 3
    ) -> None:
        if not 0 <= decimals <= MAX_DECIMALS:
            raise ValueError(f"decimals must be in 0..{MAX_DECIMALS}, found {decimals}")
        self.path = Path(path)
        self.labels_path = None if labels_path is None else Path(labels_path)
        self.decimals = decimals
        self.n_points = 0
        self.label_counts = np.zeros(256, np.int64)
        """Points written with each label value (with a labels path)."""
        self._limit = 9.0e18 / 10.0**decimals
        self._staged = [StagedPath(self.path)]
        if self.labels_path is not None:
            self._staged.append(StagedPath(self.labels_path))
        self._stream = self._staged[0].temp.open("wb")
        self._labels_stream: BinaryIO | None = None
        try:
            if self.labels_path is not None:
                self._labels_stream = self._staged[1].temp.open("wb")
        except BaseException:
            self.abort()
            raise

    def write(self, cloud: PointCloud) -> None:
        """Append ``cloud``; it must carry labels when the writer has a labels path."""
        if self._labels_stream is not None and cloud.labels is None:
            raise DataFormatError(
                "expected points with labels (the writer has a labels file), found none",
                path=str(self.path),
            )
        for start in range(0, cloud.n_points, _FORMAT_BATCH):
            batch = cloud[start : start + _FORMAT_BATCH]
            self._write_batch(batch)
            self.n_points += batch.n_points

    def _write_batch(self, batch: PointCloud) -> None:
        import numba

        from semantic3d.io import _ascii_kernels as kernels

        xyz = np.ascontiguousarray(batch.xyz)
        labels = batch.labels if self._labels_stream is not None else None
        n_threads = numba.get_num_threads()
        # several segments a thread, taken as threads come free: the end waits for less
        n_segments = max(1, min(4 * n_threads, batch.n_points // 4096))
        buffers, used, label_text, label_used, counts, bad = kernels.format_points(
            xyz,
            np.ascontiguousarray(batch.intensity),
            np.ascontiguousarray(batch.rgb),
            _NO_LABELS if labels is None else np.ascontiguousarray(labels, np.uint8),
            self.decimals,
            self._limit,
            n_segments,
            n_threads,
        )
        if bad < batch.n_points:
            raise DataFormatError(
                f"point #{self.n_points + bad}: expected finite coordinates below "
                f"{self._limit:.3g} m, found {xyz[bad].tolist()}",
                path=str(self.path),
            )
        for segment in range(n_segments):
            self._stream.write(buffers[segment, : used[segment]].data)
        if self._labels_stream is not None:
            for segment in range(n_segments):
                self._labels_stream.write(label_text[segment, : label_used[segment]].data)
            self.label_counts += counts

    def close(self) -> None:
        """Flush and close the files and move them to their final names."""
        if self._stream.closed:
            return
        self._close_streams()
        for staged in reversed(self._staged):  # the labels first: points mean "complete"
            staged.commit()

    def abort(self) -> None:
        """Close and remove what was written; the final names are left untouched."""
        self._close_streams()
        for staged in self._staged:
            staged.discard()

    def _close_streams(self) -> None:
        self._stream.close()
        if self._labels_stream is not None:
            self._labels_stream.close()


def open_ascii_writer(
    path: str | Path, *, labels_path: str | Path | None = None, decimals: int = 3
) -> AsciiPointWriter:
    """Open an :class:`AsciiPointWriter`; use it as a context manager."""
    return AsciiPointWriter(path, labels_path=labels_path, decimals=decimals)


def write_ascii_points(
    path: str | Path,
    chunks: Iterable[PointCloud],
    *,
    labels_path: str | Path | None = None,
    decimals: int = 3,
) -> int:
    """Write point chunks to ``path`` (and their labels to ``labels_path``); return the count."""
    return write_chunks(open_ascii_writer(path, labels_path=labels_path, decimals=decimals), chunks)
