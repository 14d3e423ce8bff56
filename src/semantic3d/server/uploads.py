"""Resumable uploads streamed straight to disk.

Protocol: create a session (declared size, optional sha256) -> ``PUT`` chunks, each at the
offset the server reports -> finalize. The bytes received so far *are* the size of
``uploads/<id>.part``: a chunk must start exactly there (append only, so no gaps), an
interrupted chunk keeps its correct prefix, and the client resumes from the reported
offset, even after a server restart. An exclusive ``flock`` on the part file keeps two
concurrent writers out (and a deletion out of a finalize); a body that stalls for
``upload_read_timeout_s`` is cut off, so a dead client cannot hold the lock. The sha256
is computed while bytes arrive when they arrive in order in this process, else by
re-reading the file when the upload is finalized.

Disk space: bytes are accepted only while the data folder keeps ``min_free_bytes`` free
after them (else 507, before any byte is read), so the database can always write and the
server never wedges on a full disk. Deleting removes the file first and records the
deletion after, so freeing space never depends on writing to the database.
"""

from __future__ import annotations

import asyncio
import errno
import fcntl
import hashlib
import logging
import os
import re
import shutil
import threading
import unicodedata
import uuid
from collections.abc import AsyncIterator, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any, BinaryIO

from sqlalchemy import func, select
from sqlalchemy.orm import Session, sessionmaker

from semantic3d.server.challenges import get_challenge
from semantic3d.server.db import lock_user, write_transaction
from semantic3d.server.errors import (
    ConflictError,
    InsufficientStorageError,
    InvalidInputError,
    NotFoundError,
    RequestTimeoutError,
    TooLargeError,
)
from semantic3d.server.models import UploadSession, utc_now
from semantic3d.server.settings import Settings

logger = logging.getLogger(__name__)

_WRITE_BUFFER = 8 << 20
_SHA256 = re.compile(r"^[0-9a-f]{64}$")


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

    def to_dict(self) -> dict[str, Any]:
        """JSON form for the API."""
        return {
            "id": self.id,
            "challenge": self.challenge,
            "size_bytes": self.size_bytes,
            "received_bytes": self.received_bytes,
            "filename": self.filename,
            "sha256": self.sha256,
            "complete": self.complete,
            "created_at": self.created_at.isoformat() if self.created_at else None,
            "expires_at": self.expires_at.isoformat() if self.expires_at else None,
        }


def part_path(settings: Settings, upload_id: str) -> Path:
    """The file holding an upload's bytes so far."""
    return settings.uploads_dir / f"{upload_id}.part"


def received_bytes(settings: Settings, upload_id: str) -> int:
    """Bytes received so far (0 if the part file is gone)."""
    try:
        return part_path(settings, upload_id).stat().st_size
    except FileNotFoundError:
        return 0


def clean_filename(filename: str) -> str:
    """A display-safe base name: no folders, no control characters, at most 200 characters."""
    name = filename.replace("\\", "/").rsplit("/", 1)[-1]
    name = "".join(ch for ch in name if unicodedata.category(ch)[0] != "C").strip()
    return name[:200] or "submission.zip"


def _state(settings: Settings, row: UploadSession, challenge: str) -> UploadState:
    return UploadState(
        id=row.id,
        challenge=challenge,
        size_bytes=row.size_bytes,
        received_bytes=received_bytes(settings, row.id),
        filename=row.filename,
        sha256=row.sha256,
        created_at=row.created_at,
        expires_at=row.expires_at,
    )


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


def create_upload(
    factory: sessionmaker[Session],
    settings: Settings,
    *,
    user_id: int,
    challenge: str,
    size_bytes: int,
    filename: str,
    sha256: str | None = None,
) -> UploadState:
    """Open an upload session, or return the caller's open one for the same file.

    A session matches when challenge, size and sha256 agree: that is how a client
    resumes an upload after it was restarted.
    """
    if size_bytes <= 0:
        raise InvalidInputError(f"size_bytes: expected a positive byte count, found {size_bytes}")
    if size_bytes > settings.max_upload_bytes:
        raise TooLargeError(
            f"upload of {size_bytes} bytes: this server accepts at most "
            f"{settings.max_upload_bytes} bytes per submission"
        )
    digest = sha256.lower() if sha256 else None
    if digest is not None and not _SHA256.match(digest):
        raise InvalidInputError("sha256: expected 64 hexadecimal digits")
    now = utc_now()
    with write_transaction(factory) as session:
        row_challenge = get_challenge(session, challenge)
        if not row_challenge.is_open:
            raise InvalidInputError(f"challenge {challenge!r} is closed to new submissions")
        if digest is not None:
            existing = session.scalars(
                select(UploadSession).where(
                    UploadSession.user_id == user_id,
                    UploadSession.challenge_id == row_challenge.id,
                    UploadSession.size_bytes == size_bytes,
                    UploadSession.sha256 == digest,
                    UploadSession.expires_at > now,
                )
            ).first()
            if existing is not None:
                return _state(settings, existing, challenge)
        lock_user(session, user_id)  # PostgreSQL: concurrent creates count one at a time
        n_open = session.scalar(
            select(func.count())
            .select_from(UploadSession)
            .where(UploadSession.user_id == user_id, UploadSession.expires_at > now)
        )
        if n_open is not None and n_open >= settings.max_open_uploads:
            raise ConflictError(
                f"you have {n_open} unfinished uploads (at most {settings.max_open_uploads}): "
                "finish or delete one first (GET /api/uploads lists them; the account page "
                "has delete buttons)"
            )
        settings.prepare_data_dir()
        check_free_space(settings, size_bytes)
        row = UploadSession(
            id=uuid.uuid4().hex,
            user_id=user_id,
            challenge_id=row_challenge.id,
            size_bytes=size_bytes,
            sha256=digest,
            filename=clean_filename(filename),
            created_at=now,
            expires_at=now + timedelta(seconds=settings.upload_session_ttl_s),
        )
        part_path(settings, row.id).touch(mode=0o600)
        session.add(row)
    logger.info("upload %s opened: %d bytes for %s", row.id, size_bytes, challenge)
    return _state(settings, row, challenge)


def get_upload(
    factory: sessionmaker[Session], settings: Settings, upload_id: str, *, user_id: int
) -> UploadState:
    """The caller's upload session as :class:`UploadState`, or :class:`NotFoundError`."""
    with factory() as session:
        row = owned_upload(session, upload_id, user_id)
        return _state(settings, row, row.challenge.name)


def list_uploads(
    factory: sessionmaker[Session], settings: Settings, *, user_id: int
) -> list[UploadState]:
    """The caller's open (unexpired) uploads, oldest first."""
    with factory() as session:
        rows = session.scalars(
            select(UploadSession)
            .where(UploadSession.user_id == user_id, UploadSession.expires_at > utc_now())
            .order_by(UploadSession.created_at)
        )
        return [_state(settings, row, row.challenge.name) for row in rows]


def owned_upload(session: Session, upload_id: str, user_id: int) -> UploadSession:
    row = (
        session.get(UploadSession, upload_id) if re.fullmatch(r"[0-9a-f]{32}", upload_id) else None
    )
    if row is None or row.user_id != user_id or row.expires_at <= utc_now():
        raise NotFoundError(f"upload {upload_id}: no such open upload on your account")
    return row


def delete_upload(factory: sessionmaker[Session], settings: Settings, upload_id: str) -> None:
    """Forget an upload session and its bytes: the file first, then the database row.

    The caller holds the upload's lock or knows nobody else uses it (see
    :func:`cancel_upload`). Removing the file first frees its space even when the database
    cannot be written (a full disk); the row left behind then points at no data and is
    removed by a later deletion or the expiry sweep.
    """
    _remove_part(settings, upload_id)
    with write_transaction(factory) as session:
        row = session.get(UploadSession, upload_id)
        if row is not None:
            session.delete(row)


def _remove_part(settings: Settings, upload_id: str) -> None:
    """Delete the part file, emptying it first: an open handle (the lock's) would else keep
    its blocks allocated until closed, after the database write that needs them."""
    path = part_path(settings, upload_id)
    with suppress(FileNotFoundError):
        os.truncate(path, 0)
    path.unlink(missing_ok=True)
    _HASHES.forget(upload_id)


def cancel_upload(
    factory: sessionmaker[Session], settings: Settings, upload_id: str, *, user_id: int
) -> None:
    """Abandon the caller's upload; :class:`ConflictError` while a request writes or finalizes it."""
    with factory() as session:
        owned_upload(session, upload_id, user_id)
    try:
        with locked_part(settings, upload_id, doing="deleted"):
            delete_upload(factory, settings, upload_id)
    except NotFoundError:  # its data is already gone: forget the session too
        delete_upload(factory, settings, upload_id)


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


def expire_uploads(factory: sessionmaker[Session], settings: Settings) -> int:
    """Delete expired upload sessions and orphaned part files; returns how many went.

    Files go first and the database rows after, so the sweep frees space even when the
    database cannot be written; an upload being written or finalized right now (locked)
    is left for the next sweep.
    """
    now = utc_now()
    with factory() as session:
        expired = list(
            session.scalars(select(UploadSession.id).where(UploadSession.expires_at <= now))
        )
        live = set(session.scalars(select(UploadSession.id)))
    gone = [upload_id for upload_id in expired if _remove_unlocked(settings, upload_id)]
    removed = len(gone)
    if settings.uploads_dir.is_dir():
        for path in settings.uploads_dir.glob("*.part"):
            if path.stem not in live and _older_than(path, 3600):
                path.unlink(missing_ok=True)
                removed += 1
    if gone:
        with write_transaction(factory) as session:
            for row in session.scalars(select(UploadSession).where(UploadSession.id.in_(gone))):
                session.delete(row)
    return removed


def _remove_unlocked(settings: Settings, upload_id: str) -> bool:
    """Delete an upload's part file unless a request holds it; whether it is gone."""
    try:
        with locked_part(settings, upload_id, doing="expired"):
            _remove_part(settings, upload_id)
    except NotFoundError:
        _HASHES.forget(upload_id)
    except ConflictError:
        return False
    return True


def _older_than(path: Path, seconds: float) -> bool:
    try:
        return utc_now().timestamp() - path.stat().st_mtime > seconds
    except FileNotFoundError:
        return False
