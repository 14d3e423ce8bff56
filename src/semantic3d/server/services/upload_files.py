"""An upload's bytes on disk: the part file, its lock, streaming chunks in, the running hash.

The bytes received so far *are* the size of ``uploads/<id>.part``: a chunk must start
exactly there (append only, so no gaps), an interrupted chunk keeps its correct prefix,
and the client resumes from the reported offset, even after a server restart. An
exclusive ``flock`` on the part file keeps two concurrent writers out (and a deletion out
of a finalize); a body that stalls for ``upload_read_timeout_s`` is cut off, so a dead
client cannot hold the lock. The sha256 is computed while bytes arrive when they arrive
in order in this process, else by re-reading the file when the upload is finalized.

Disk space: bytes are accepted only while the data folder keeps ``min_free_bytes`` free
after them (else 507, before any byte is read), so the database can always write and the
server never wedges on a full disk.
"""

from __future__ import annotations

import asyncio
import errno
import fcntl
import hashlib
import os
import shutil
import threading
from collections.abc import AsyncIterator, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any, BinaryIO

from semantic3d.server.errors import (
    ConflictError,
    InsufficientStorageError,
    NotFoundError,
    RequestTimeoutError,
    TooLargeError,
)
from semantic3d.server.schemas import UploadInfo
from semantic3d.server.settings import Settings

_WRITE_BUFFER = 8 << 20


@dataclass(frozen=True, slots=True)
class UploadState:
    """What a client needs to continue an upload."""

    id: str
    challenge: str
    size_bytes: int
    received_bytes: int
    filename: str
    sha256: str | None
    created_at: datetime | None = None
    expires_at: datetime | None = None

    @property
    def complete(self) -> bool:
        """Whether every declared byte has arrived."""
        return self.received_bytes >= self.size_bytes

    def to_info(self) -> UploadInfo:
        """The API's view of the upload."""
        return UploadInfo(
            id=self.id,
            challenge=self.challenge,
            size_bytes=self.size_bytes,
            received_bytes=self.received_bytes,
            filename=self.filename,
            sha256=self.sha256,
            complete=self.complete,
            created_at=self.created_at,
            expires_at=self.expires_at,
        )


def part_path(settings: Settings, upload_id: str) -> Path:
    """The file holding an upload's bytes so far."""
    return settings.uploads_dir / f"{upload_id}.part"


def stored_name_of(upload_id: str) -> str:
    """The name an accepted upload's file takes under ``submissions/``."""
    return f"{upload_id}.zip"


def sync_folders(*folders: Path) -> None:
    """``fsync`` folders, so that renames into or out of them survive a power cut."""
    for folder in dict.fromkeys(folders):
        fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def received_bytes(settings: Settings, upload_id: str) -> int:
    """Bytes received so far (0 if the part file is gone)."""
    try:
        return part_path(settings, upload_id).stat().st_size
    except FileNotFoundError:
        return 0


def check_free_space(settings: Settings, n_bytes: int) -> None:
    """Raise :class:`InsufficientStorageError` unless ``n_bytes`` more leave the margin free.

    The margin is ``settings.min_free_bytes`` on the data folder's file system.
    """
    folder = settings.uploads_dir if settings.uploads_dir.is_dir() else settings.data_dir
    free = shutil.disk_usage(folder).free
    if free - n_bytes < settings.min_free_bytes:
        raise InsufficientStorageError(
            f"not enough free disk space on the server for {n_bytes} more bytes "
            f"(it keeps {settings.min_free_bytes} bytes free); nothing was stored, try "
            "again later"
        )


def remove_part(settings: Settings, upload_id: str) -> None:
    """Delete the part file, emptying it first: an open handle (the lock's) would else keep
    its blocks allocated until closed, after the database write that needs them."""
    path = part_path(settings, upload_id)
    with suppress(FileNotFoundError):
        os.truncate(path, 0)
    path.unlink(missing_ok=True)
    _HASHES.forget(upload_id)


@contextmanager
def locked_part(
    settings: Settings, upload_id: str, *, doing: str = "written to"
) -> Iterator[BinaryIO]:
    """The upload's part file, opened for update under an exclusive lock.

    One request at a time writes to, finalizes or deletes an upload: others get
    :class:`ConflictError` at once (the lock is ``flock``, so it holds across processes).
    """
    try:
        # Unbuffered: a failed write leaves nothing pending that a later flush could put
        # in the wrong place.
        handle = part_path(settings, upload_id).open("r+b", buffering=0)
    except FileNotFoundError:
        raise NotFoundError(f"upload {upload_id}: its data is gone; start a new upload") from None
    with handle:
        try:
            fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise ConflictError(
                f"upload {upload_id} cannot be {doing} now: another request is writing or "
                "finalizing it; try again when it has finished",
                offset=None,
            ) from None
        yield handle


async def write_chunk(
    settings: Settings,
    upload: UploadState,
    *,
    offset: int,
    content_length: int | None,
    chunks: AsyncIterator[bytes],
) -> int:
    """Append a request body at ``offset`` to the upload; returns the new received size.

    Raises :class:`ConflictError` (carrying the right offset) if ``offset`` is not where
    the upload stands or another request is writing to it, :class:`TooLargeError` if the
    body would pass the declared size or the chunk limit (the part file is cut back to
    ``offset``), :class:`InsufficientStorageError` if the disk cannot take the chunk and
    keep ``min_free_bytes`` free (checked before reading; a write that fails for space is
    cut back too) and :class:`RequestTimeoutError` when no byte came for
    ``upload_read_timeout_s``. A dropped or stalled connection keeps the bytes that arrived.
    """
    limit = upload.size_bytes - offset
    if content_length is not None and content_length > settings.max_chunk_bytes:
        raise TooLargeError(
            f"chunk of {content_length} bytes: at most {settings.max_chunk_bytes} bytes per PUT"
        )
    if content_length is not None and content_length > limit:
        raise TooLargeError(
            f"chunk of {content_length} bytes at offset {offset} passes the declared size "
            f"{upload.size_bytes}"
        )
    cap = min(limit, settings.max_chunk_bytes)
    check_free_space(settings, cap if content_length is None else content_length)
    with locked_part(settings, upload.id) as handle:
        current = os.fstat(handle.fileno()).st_size
        if offset != current:
            raise ConflictError(
                f"upload {upload.id}: chunk at offset {offset}, but {current} bytes are "
                f"received; send from offset {current}",
                offset=current,
            )
        handle.seek(offset)
        # Double buffering: while one block is written and hashed on a thread (both release
        # the GIL), the event loop keeps receiving the next one.
        queued = 0  # bytes handed to the writer, written or in progress
        pending: Future[None] | None = None
        buffer = bytearray()
        loop = asyncio.get_running_loop()
        read_timeout_s = settings.upload_read_timeout_s

        def hand_over(block: bytearray) -> Future[None]:
            return _WRITER.submit(_append, handle, upload.id, offset + queued, block)

        try:
            # The deadline moves with the data, at most every ``step`` s (rescheduling a
            # timer for each 64 KiB piece would cost ~8 us x 16 k pieces per GiB).
            step = min(1.0, read_timeout_s / 4)
            moved = loop.time()
            async with asyncio.timeout(read_timeout_s) as deadline:
                async for piece in chunks:
                    now = loop.time()
                    if now - moved > step:
                        deadline.reschedule(now + read_timeout_s)
                        moved = now
                    if queued + len(buffer) + len(piece) > cap:
                        raise TooLargeError(
                            f"chunk at offset {offset} passes the declared size "
                            f"{upload.size_bytes} or the {settings.max_chunk_bytes}-byte "
                            "chunk limit"
                        )
                    buffer += piece
                    if len(buffer) >= _WRITE_BUFFER:
                        if pending is not None:
                            await asyncio.wrap_future(pending)
                        pending = hand_over(buffer)
                        queued += len(buffer)
                        buffer = bytearray()
                if pending is not None:
                    await asyncio.wrap_future(pending)
                if buffer:
                    pending = hand_over(buffer)
                    queued += len(buffer)
                    buffer = bytearray()
                    await asyncio.wrap_future(pending)
        except TimeoutError:
            _keep_received(handle, upload.id, offset + queued, pending, buffer)
            raise RequestTimeoutError(
                f"upload {upload.id}: no data for {read_timeout_s:g} s; the bytes received "
                "are kept, resume from GET /api/uploads/{id}"
            ) from None
        except (TooLargeError, OSError) as exc:
            if pending is not None:
                _wait_quietly(pending)
            handle.truncate(offset)
            _HASHES.forget(upload.id)
            if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT):
                raise InsufficientStorageError(
                    f"the server's disk filled up while receiving the chunk at offset "
                    f"{offset}; nothing of it was kept, try again later"
                ) from None
            raise
        except BaseException:
            # Dropped connection or cancellation: keep the bytes that did arrive.
            _keep_received(handle, upload.id, offset + queued, pending, buffer)
            raise
        return offset + queued


def _wait_quietly(pending: Future[None]) -> None:
    with suppress(OSError):
        pending.result()


def _keep_received(
    handle: Any, upload_id: str, position: int, pending: Future[None] | None, buffer: bytearray
) -> None:
    """Flush what arrived before the body stopped (``position``: where ``buffer`` goes)."""
    if pending is not None:
        pending.result()
    if buffer:
        _append(handle, upload_id, position, buffer)


_WRITER = ThreadPoolExecutor(max_workers=8, thread_name_prefix="semantic3d-upload")


def _append(handle: Any, upload_id: str, position: int, block: bytearray) -> None:
    view = memoryview(block)
    while view:
        view = view[handle.write(view) :]
    _HASHES.update(upload_id, position, block)


class _RunningHashes:
    """Per-process sha256 state of uploads whose bytes arrived in order."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._state: dict[str, tuple[Any, int]] = {}

    def update(self, upload_id: str, position: int, block: bytearray) -> None:
        with self._lock:
            state = self._state.get(upload_id)
        if state is None and position == 0:
            state = (hashlib.sha256(), 0)
        if state is None or state[1] != position:
            self.forget(upload_id)
            return
        hasher = state[0]
        hasher.update(block)
        with self._lock:
            self._state[upload_id] = (hasher, position + len(block))

    def digest(self, upload_id: str, size: int) -> str | None:
        with self._lock:
            state = self._state.get(upload_id)
        if state is None or state[1] != size:
            return None
        return state[0].hexdigest()

    def forget(self, upload_id: str) -> None:
        with self._lock:
            self._state.pop(upload_id, None)


_HASHES = _RunningHashes()


def file_sha256(path: Path) -> str:
    """The sha256 of a file, read in 8 MiB blocks."""
    hasher = hashlib.sha256()
    with path.open("rb") as handle:
        while block := handle.read(_WRITE_BUFFER):
            hasher.update(block)
    return hasher.hexdigest()


def upload_sha256(settings: Settings, upload_id: str, size: int) -> str:
    """The sha256 of a complete upload (running hash if available, else re-read)."""
    digest = _HASHES.digest(upload_id, size)
    return digest if digest is not None else file_sha256(part_path(settings, upload_id))


def forget_hash(upload_id: str) -> None:
    """Drop the running hash of an upload (deleted, or its bytes no longer in order)."""
    _HASHES.forget(upload_id)
