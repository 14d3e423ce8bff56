"""Resumable uploads streamed straight to disk.

Protocol: create a session (declared size, optional sha256) -> ``PUT`` chunks, each at the
offset the server reports -> finalize. The bytes received so far *are* the size of
``uploads/<id>.part``: a chunk must start exactly there (append only, so no gaps), an
interrupted chunk keeps its correct prefix, and the client resumes from the reported
offset, even after a server restart. An exclusive ``flock`` on the part file keeps two
concurrent writers out. The sha256 is computed while bytes arrive when they arrive in
order in this process, else by re-reading the file when the upload is finalized.
"""

from __future__ import annotations

import asyncio
import fcntl
import hashlib
import logging
import os
import re
import threading
import unicodedata
import uuid
from collections.abc import AsyncIterator, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import timedelta
from pathlib import Path
from typing import Any, BinaryIO

from sqlalchemy import func, select
from sqlalchemy.orm import Session, sessionmaker

from semantic3d.server.challenges import get_challenge
from semantic3d.server.db import lock_user, write_transaction
from semantic3d.server.errors import ConflictError, InvalidInputError, NotFoundError, TooLargeError
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
                "finish or delete one first"
            )
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
        settings.prepare_data_dir()
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


def owned_upload(session: Session, upload_id: str, user_id: int) -> UploadSession:
    row = (
        session.get(UploadSession, upload_id) if re.fullmatch(r"[0-9a-f]{32}", upload_id) else None
    )
    if row is None or row.user_id != user_id or row.expires_at <= utc_now():
        raise NotFoundError(f"upload {upload_id}: no such open upload on your account")
    return row


def delete_upload(factory: sessionmaker[Session], settings: Settings, upload_id: str) -> None:
    """Forget an upload session and its bytes."""
    with write_transaction(factory) as session:
        row = session.get(UploadSession, upload_id)
        if row is not None:
            session.delete(row)
    part_path(settings, upload_id).unlink(missing_ok=True)
    _HASHES.forget(upload_id)


@contextmanager
def locked_part(settings: Settings, upload_id: str) -> Iterator[BinaryIO]:
    """The upload's part file, opened for update under an exclusive lock.

    One request at a time writes to or finalizes an upload: others get
    :class:`ConflictError` at once (the lock is ``flock``, so it holds across processes).
    """
    try:
        handle = part_path(settings, upload_id).open("r+b")
    except FileNotFoundError:
        raise NotFoundError(f"upload {upload_id}: its data is gone; start a new upload") from None
    with handle:
        try:
            fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise ConflictError(
                f"upload {upload_id}: another request is writing or finalizing it", offset=None
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
    the upload stands or another request is writing to it, and :class:`TooLargeError`
    if the body would pass the declared size or the chunk limit (the part file is cut
    back to ``offset``). A dropped connection keeps the bytes that arrived.
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
    with locked_part(settings, upload.id) as handle:
        current = os.fstat(handle.fileno()).st_size
        if offset != current:
            raise ConflictError(
                f"upload {upload.id}: chunk at offset {offset}, but {current} bytes are "
                f"received; send from offset {current}",
                offset=current,
            )
        handle.seek(offset)
        cap = min(limit, settings.max_chunk_bytes)
        # Double buffering: while one block is written and hashed on a thread (both release
        # the GIL), the event loop keeps receiving the next one.
        queued = 0  # bytes handed to the writer, written or in progress
        pending: Future[None] | None = None
        buffer = bytearray()

        def hand_over(block: bytearray) -> Future[None]:
            return _WRITER.submit(_append, handle, upload.id, offset + queued, block)

        try:
            async for piece in chunks:
                if queued + len(buffer) + len(piece) > cap:
                    raise TooLargeError(
                        f"chunk at offset {offset} passes the declared size "
                        f"{upload.size_bytes} or the {settings.max_chunk_bytes}-byte chunk limit"
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
        except TooLargeError:
            if pending is not None:
                pending.result()
            handle.truncate(offset)
            _HASHES.forget(upload.id)
            raise
        except BaseException:
            # Dropped connection or cancellation: keep the bytes that did arrive.
            if pending is not None:
                pending.result()
            if buffer:
                _append(handle, upload.id, offset + queued, buffer)
            raise
        return offset + queued


_WRITER = ThreadPoolExecutor(max_workers=8, thread_name_prefix="semantic3d-upload")


def _append(handle: Any, upload_id: str, position: int, block: bytearray) -> None:
    handle.write(block)
    handle.flush()
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
    """Delete expired upload sessions and orphaned part files; returns how many went."""
    now = utc_now()
    with write_transaction(factory) as session:
        expired = list(
            session.scalars(select(UploadSession).where(UploadSession.expires_at <= now))
        )
        for row in expired:
            session.delete(row)
        live = set(session.scalars(select(UploadSession.id)))
    removed = 0
    for row in expired:
        part_path(settings, row.id).unlink(missing_ok=True)
        _HASHES.forget(row.id)
        removed += 1
    if settings.uploads_dir.is_dir():
        for path in settings.uploads_dir.glob("*.part"):
            if path.stem not in live and _older_than(path, 3600):
                path.unlink(missing_ok=True)
                removed += 1
    return removed


def _older_than(path: Path, seconds: float) -> bool:
    try:
        return utc_now().timestamp() - path.stat().st_mtime > seconds
    except FileNotFoundError:
        return False
