"""``.labels`` files: one non-negative integer per line (the benchmark's label format).

Reading streams the file in blocks of whole lines. The benchmark's files hold one digit
per line (``0``..``8``); those take a compiled fast path over all cores that validates
every byte: :func:`read_labels` reads and parses blocks of the file on every thread in
compiled code, each straight into its slice of the result (no thread waits for another's
read, nor for the interpreter). Any
other shape (CRLF line ends, blanks, several digits) falls back for that block to the
checking parser :class:`~semantic3d.io.labelstream.LabelStream` runs
(one parser for both: ``_label_parsing.parse_lines``; small files are parsed with numpy,
long ones by compiled kernels, with the same results). Values above 255 are rejected:
labels are ``uint8``. To read a stream that is not a path (a zip member), or to collect
every bad line rather than stop at the first, use ``LabelStream``.
"""

from __future__ import annotations

import io
import os
import stat
from collections.abc import Generator, Iterable, Iterator
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from semantic3d.core.errors import DataFormatError
from semantic3d.core.pointcloud import PointCloud
from semantic3d.io import _label_grammar as grammar
from semantic3d.io import _label_parsing as parsing
from semantic3d.io.chunks import (
    DEFAULT_BLOCK_BYTES,
    DEFAULT_CHUNK_SIZE,
    concatenate_arrays,
    iter_line_blocks,
    line_text,
    rechunk,
    validate_chunk_size,
)
from semantic3d.io.staging import StagedPath

MAX_LABEL_VALUE = 255

__all__ = [
    "attach_labels",
    "count_labels",
    "format_labels_bytes",
    "iter_labels",
    "read_labels",
    "write_labels",
]


def iter_labels(
    path: str | Path,
    *,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
    block_bytes: int = DEFAULT_BLOCK_BYTES,
) -> Iterator[NDArray[np.uint8]]:
    """Stream the labels of ``path`` as uint8 arrays of exactly ``chunk_size`` values.

    The last chunk may be shorter; an empty file yields nothing. Raises
    :class:`~semantic3d.core.errors.DataFormatError` naming the file and line of the first
    empty line, non-integer or value above 255.
    """
    chunk_size = validate_chunk_size(chunk_size)
    return _iter_labels(Path(path), chunk_size, block_bytes)


def _iter_labels(path: Path, chunk_size: int, block_bytes: int) -> Iterator[NDArray[np.uint8]]:
    done, complete = yield from _iter_mapped_single_digit(path, chunk_size)
    if complete:
        return
    # Not (only) one digit a line: the checking parser, from the start, past what was given.
    chunks = rechunk(_iter_label_blocks(path, block_bytes), chunk_size, concatenate_arrays)
    for chunk in chunks:
        if done >= chunk.size:
            done -= chunk.size
            continue
        yield chunk[done:]
        done = 0


def _iter_mapped_single_digit(
    path: Path, chunk_size: int
) -> Generator[NDArray[np.uint8], None, tuple[int, bool]]:
    """The labels of a file of ``d\n`` lines, read chunk by chunk into one reused buffer
    and parsed from it into each chunk (in parallel); stops at the first chunk of another
    shape. Returns ``(labels yielded, whether that was the whole file)``."""
    size = _pairs_file_size(path)
    if size is None:
        return 0, False
    n = size // 2
    buffer = np.empty(2 * min(chunk_size, n), np.uint8)
    with path.open("rb", buffering=0) as stream:
        for start in range(0, n, chunk_size):
            stop = min(start + chunk_size, n)
            text = buffer[: 2 * (stop - start)]
            out = np.empty(stop - start, np.uint8)
            if _read_fully(stream, text) != text.size or parsing.parse_single_digit(text, out):
                return start, False
            yield out
    return n, True


_PIECE_LABELS = 1 << 25
"""Labels :func:`read_labels` reads in one call of the compiled reader (64 MiB of text):
Ctrl-C is seen between calls."""
_BLOCK_LINES = 0
"""Lines each thread reads at a time (0: the compiled reader's own, 512 KiB of text)."""


def _pairs_file_size(path: Path) -> int | None:
    """The size of a large regular file of even size (what ``d\n`` lines make), else None."""
    try:
        status = path.stat()
    except OSError:
        return None
    size = status.st_size
    if not stat.S_ISREG(status.st_mode) or size % 2 or size <= parsing.SMALL_TEXT_BYTES:
        return None
    return int(size)


def _read_fully(stream: io.RawIOBase, buffer: NDArray[np.uint8]) -> int:
    """Fill ``buffer`` from ``stream`` (a raw file); the bytes read (fewer only at the end)."""
    view = memoryview(buffer.data)
    done = 0
    while done < len(view):
        read = stream.readinto(view[done:])
        if not read:
            break
        done += read
    return done


def _read_single_digit(path: Path) -> NDArray[np.uint8] | None:
    """All labels of a file of ``d\n`` lines, else None (another shape, a small file, or
    a platform without positioned reads).

    Compiled code reads the file itself: each of the thread budget's threads reads its own
    blocks with ``pread`` into a buffer that stays in its cache and converts them into its
    slice of the result (disjoint slices, so the result is the same for any count). No
    interpreter between blocks: with the reads and the parse in the interpreter's hands,
    16 threads queued for its lock and the blocks' copies left the cache.
    """
    size = _pairs_file_size(path)
    if size is None or not hasattr(os, "pread"):
        return None
    n = size // 2
    out = np.empty(n, np.uint8)
    try:
        with path.open("rb", buffering=0) as stream:
            fd = stream.fileno()
            for start in range(0, n, _PIECE_LABELS):
                piece = out[start : start + _PIECE_LABELS]
                if not parsing.read_single_digit_file(fd, start, piece, block_lines=_BLOCK_LINES):
                    return None  # another shape, or the file shrank: the checking reader says
    except OSError:
        return None
    return out


def read_labels(path: str | Path) -> NDArray[np.uint8]:
    """All labels of ``path`` as one uint8 array.

    A file of ``d\n`` lines (the benchmark's) is read in blocks, each read and parsed into
    the result by one of the thread budget's threads; any other shape is read as
    :func:`iter_labels` reads it.
    """
    path = Path(path)
    labels = _read_single_digit(path)
    if labels is not None:
        return labels
    chunks = list(iter_labels(path))
    return concatenate_arrays(chunks) if chunks else np.empty(0, np.uint8)


def count_labels(path: str | Path) -> int:
    """Number of labels in ``path``, validating every line as :func:`iter_labels` does."""
    return sum(len(block) for block in _iter_label_blocks(Path(path), DEFAULT_BLOCK_BYTES))


def write_labels(path: str | Path, chunks: Iterable[ArrayLike]) -> int:
    """Write label chunks to ``path``, one decimal integer per line; return the count.

    Values must be integers in 0..255. The file streams to a temporary name and is renamed
    into place when complete (:class:`~semantic3d.io.staging.StagedPath`): on an error or
    Ctrl-C, ``path`` is left as it was.
    """
    path = Path(path)
    staged = StagedPath(path)
    written = 0
    try:
        with staged.temp.open("wb") as stream:
            for chunk in chunks:
                labels = _as_label_array(chunk, path=path, first_index=written)
                if labels.size == 0:
                    continue
                stream.write(format_labels_bytes(labels))
                written += labels.size
    except BaseException:
        staged.discard()
        raise
    staged.commit()
    return written


def format_labels_bytes(labels: NDArray[np.uint8]) -> memoryview:
    """``labels`` (uint8) as ``.labels`` text: one decimal value per line."""
    if labels.size and labels.max() <= 9:
        # The benchmark's case: "d\n" pairs, built with two strided stores.
        text = np.empty(2 * labels.size, np.uint8)
        text[0::2] = labels + 48
        text[1::2] = 10
        return text.data
    from semantic3d.io import _label_kernels as kernels

    text = np.empty(4 * labels.size, np.uint8)
    used = kernels.format_labels(np.ascontiguousarray(labels), text)
    return text[:used].data


def attach_labels(
    path: Path, clouds: Iterator[PointCloud], labels_path: Path, *, chunk_size: int
) -> Iterator[PointCloud]:
    """Pair point chunks of ``path`` with the labels of ``labels_path``, chunk for chunk.

    ``clouds`` must be chunks of exactly ``chunk_size`` points (the last may be shorter).
    A label file with another number of lines raises :class:`DataFormatError`.
    """
    label_chunks = iter_labels(labels_path, chunk_size=chunk_size)
    n_points = 0
    for cloud in clouds:
        labels = next(label_chunks, None)
        n_labels = n_points + (0 if labels is None else labels.size)
        n_points += cloud.n_points
        if labels is None or labels.size < cloud.n_points:
            raise DataFormatError(
                f"expected one label per point of {path.name}, found only {n_labels} labels "
                f"for at least {n_points} points",
                path=str(labels_path),
            )
        if labels.size > cloud.n_points:  # only the last point chunk can be short
            n_labels += sum(chunk.size for chunk in label_chunks)
            break
        yield cloud.with_labels(labels)
    else:
        n_labels = n_points + sum(chunk.size for chunk in label_chunks)
        if n_labels == n_points:
            return
    raise DataFormatError(
        f"expected one label per point of {path.name} ({n_points} points), found {n_labels} labels",
        path=str(labels_path),
    )


def _as_label_array(chunk: ArrayLike, *, path: Path, first_index: int) -> NDArray[np.uint8]:
    array = np.asarray(chunk)
    if array.ndim != 1:
        raise DataFormatError(
            f"expected a 1-d array of labels, found shape {array.shape}", path=str(path)
        )
    if array.dtype == np.uint8:
        return np.ascontiguousarray(array)
    if array.size and not np.issubdtype(array.dtype, np.integer):
        raise DataFormatError(f"expected integer labels, found dtype {array.dtype}", path=str(path))
    if array.size and (array.min() < 0 or array.max() > MAX_LABEL_VALUE):
        bad = int(np.flatnonzero((array < 0) | (array > MAX_LABEL_VALUE))[0])
        raise DataFormatError(
            f"label #{first_index + bad} is {int(array[bad])}: expected 0..{MAX_LABEL_VALUE}",
            path=str(path),
        )
    return array.astype(np.uint8)


def _iter_label_blocks(path: Path, block_bytes: int) -> Iterator[NDArray[np.uint8]]:
    first_line = 1
    for block in iter_line_blocks(path, block_bytes=block_bytes):
        labels = _parse_block(block)
        if isinstance(labels, tuple):
            line, detail = labels
            raise DataFormatError(detail, path=str(path), line=first_line - 1 + line)
        first_line += labels.size
        yield labels


def _parse_block(block: NDArray[np.uint8]) -> NDArray[np.uint8] | tuple[int, str]:
    """The labels of a block of whole lines, or its first bad line (1-based) and what is wrong.

    The benchmark's one-digit lines go through the parallel fast path; anything else
    through the checking parser :class:`~semantic3d.io.labelstream.LabelStream` uses.
    """
    if block.size % 2 == 0:
        fast = np.empty(block.size // 2, np.uint8)
        if parsing.parse_single_digit(block, fast) == 0:
            return fast
    n_lines = int(np.count_nonzero(block == 10))  # blocks end with a newline
    out = np.empty(n_lines, np.uint8)
    state = np.zeros(grammar.STATE_SIZE, np.int64)
    text = np.zeros(grammar.TEXT_BYTES, np.uint8)
    parsing.parse_lines(
        block, 0, block.size, True, out, 0, n_lines, 0, MAX_LABEL_VALUE, state, text
    )
    problems = [
        (int(state[grammar.SYNTAX_LINE]), True) if state[grammar.N_SYNTAX] else None,
        (int(state[grammar.RANGE_LINE]), False) if state[grammar.N_RANGE] else None,
    ]
    found = [problem for problem in problems if problem is not None]
    if not found:
        return out
    line, syntax = min(found)
    shown = line_text(block, line - 1).strip()
    if syntax and not shown:
        detail = "expected one integer label, found an empty line"
    elif syntax:
        detail = f"expected one non-negative integer label, found {shown!r}"
    else:
        detail = f"expected a label value in 0..{MAX_LABEL_VALUE}, found {shown!r}"
    return line, detail
