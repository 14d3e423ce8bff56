"""Chunking helpers shared by every streaming reader.

Readers parse whatever block of a file is convenient and hand the pieces to
:func:`rechunk`, so callers always see chunks of exactly ``chunk_size`` points (the last
may be shorter), whatever the format: points and labels read from two files line up
chunk for chunk.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path
from typing import Protocol, TypeVar

import numpy as np

from semantic3d.core.errors import DataFormatError

DEFAULT_CHUNK_SIZE = 1 << 20
"""Points per chunk unless a caller asks otherwise (about 30 MB of arrays)."""

DEFAULT_BLOCK_BYTES = 32 << 20
"""Bytes of text read and parsed at once by the ASCII readers."""

_MAX_LINE_BYTES = 1 << 20


class _Sliceable(Protocol):
    def __len__(self) -> int: ...
    def __getitem__(self, index: slice) -> _Sliceable: ...


T = TypeVar("T", bound=_Sliceable)


def validate_chunk_size(chunk_size: int) -> int:
    """Return ``chunk_size`` as an int, or raise ``ValueError`` when it is not positive."""
    if int(chunk_size) != chunk_size or chunk_size < 1:
        raise ValueError(f"chunk_size must be a positive integer, found {chunk_size!r}")
    return int(chunk_size)


def rechunk(
    pieces: Iterable[T], chunk_size: int, concatenate: Callable[[Sequence[T]], T]
) -> Iterator[T]:
    """Regroup ``pieces`` of any lengths into chunks of exactly ``chunk_size`` items.

    The last chunk holds the remainder; no empty chunk is yielded. Pieces at least as long
    as a chunk are sliced without copying; only pieces straddling a boundary are joined.
    """
    chunk_size = validate_chunk_size(chunk_size)
    pending: list[T] = []
    n_pending = 0
    for piece in pieces:
        start, length = 0, len(piece)
        while start < length:
            if n_pending == 0 and length - start >= chunk_size:
                yield piece[start : start + chunk_size]  # type: ignore[misc]
                start += chunk_size
                continue
            take = min(chunk_size - n_pending, length - start)
            pending.append(piece[start : start + take])  # type: ignore[arg-type]
            n_pending += take
            start += take
            if n_pending == chunk_size:
                yield concatenate(pending)
                pending, n_pending = [], 0
    if n_pending:
        yield concatenate(pending)


def concatenate_arrays(arrays: Sequence[np.ndarray]) -> np.ndarray:
    """``np.concatenate`` that returns the only array untouched."""
    return arrays[0] if len(arrays) == 1 else np.concatenate(arrays)


def iter_line_blocks(path: Path, *, block_bytes: int = DEFAULT_BLOCK_BYTES) -> Iterator[np.ndarray]:
    """Yield uint8 blocks of ``path`` that hold only whole lines, each ending in ``\\n``.

    A missing final newline is supplied. The yielded array is a view of a reused buffer:
    parse it before asking for the next block. A line longer than 1 MiB is rejected (no
    point or label file has one; it means the file is binary or not line based).
    """
    # Reusing one buffer with readinto avoids an allocation and a copy per block.
    buffer = np.empty(block_bytes + 1, dtype=np.uint8)
    view = memoryview(buffer)  # type: ignore[arg-type]
    carry = 0
    with Path(path).open("rb", buffering=0) as stream:
        while True:
            n_read = stream.readinto(view[carry:block_bytes])
            filled = carry + (n_read or 0)
            if not n_read:
                if carry:
                    buffer[carry] = 10  # the missing final newline
                    yield buffer[: carry + 1]
                return
            cut = _last_newline(buffer, filled)
            if cut < 0:
                if filled >= block_bytes:
                    if block_bytes >= _MAX_LINE_BYTES:
                        raise DataFormatError(
                            f"expected text lines, found a line longer than {_MAX_LINE_BYTES} "
                            "bytes (binary data?)",
                            path=str(path),
                        )
                    buffer = _grown(buffer, filled)
                    view = memoryview(buffer)  # type: ignore[arg-type]
                    block_bytes = buffer.shape[0] - 1
                carry = filled
                continue
            yield buffer[: cut + 1]
            rest = filled - cut - 1
            if rest:
                buffer[:rest] = buffer[cut + 1 : filled].copy()
            carry = rest


def _grown(buffer: np.ndarray, filled: int) -> np.ndarray:
    bigger = np.empty(min(2 * buffer.shape[0], _MAX_LINE_BYTES + 1), dtype=np.uint8)
    bigger[:filled] = buffer[:filled]
    return bigger


def _last_newline(buffer: np.ndarray, filled: int) -> int:
    """Index of the last ``\\n`` in ``buffer[:filled]``, or -1."""
    # Lines are short: look at a small tail first, the whole block only if needed.
    tail = max(0, filled - 4096)
    hits = np.flatnonzero(buffer[tail:filled] == 10)
    if hits.size:
        return tail + int(hits[-1])
    hits = np.flatnonzero(buffer[:tail] == 10)
    return int(hits[-1]) if hits.size else -1


def line_text(block: np.ndarray, line: int, limit: int = 200) -> str:
    """The text of 0-based ``line`` of a block of whole lines, for error messages."""
    ends = np.flatnonzero(block == 10)
    start = 0 if line == 0 else int(ends[line - 1]) + 1
    end = int(ends[line]) if line < ends.size else block.size
    raw = bytes(block[start : min(end, start + limit)])
    return raw.decode("utf-8", errors="replace").rstrip("\r")
