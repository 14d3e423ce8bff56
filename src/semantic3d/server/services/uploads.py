"""Resumable upload sessions: open (or resume), look up, list, cancel and expire them.

Protocol: create a session (declared size, optional sha256) -> ``PUT`` chunks, each at the
offset the server reports (:mod:`.upload_files` streams them to disk) -> finalize
(:mod:`.submissions`). Deleting removes the file first and records the deletion after,
so freeing space never depends on writing to the database.
"""

from __future__ import annotations

import logging
import re
import unicodedata
import uuid
from datetime import timedelta
from pathlib import Path

from sqlalchemy import func, select
from sqlalchemy.orm import Session, sessionmaker

from semantic3d.server.db import lock_user, write_transaction
from semantic3d.server.errors import ConflictError, InvalidInputError, NotFoundError, TooLargeError
from semantic3d.server.models import UploadSession, utc_now
from semantic3d.server.services.challenges import get_challenge
from semantic3d.server.services.upload_files import (
    UploadState,
    check_free_space,
    forget_hash,
    locked_part,
    part_path,
    received_bytes,
    remove_part,
)
from semantic3d.server.settings import Settings

logger = logging.getLogger(__name__)

_SHA256 = re.compile(r"^[0-9a-f]{64}$")

__all__ = [
    "UploadState",
    "cancel_upload",
    "clean_filename",
    "create_upload",
    "delete_upload",
    "expire_uploads",
    "get_upload",
    "list_uploads",
    "owned_upload",
]


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
    remove_part(settings, upload_id)
    with write_transaction(factory) as session:
        row = session.get(UploadSession, upload_id)
        if row is not None:
            session.delete(row)


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
            remove_part(settings, upload_id)
    except NotFoundError:
        forget_hash(upload_id)
    except ConflictError:
        return False
    return True


def _older_than(path: Path, seconds: float) -> bool:
    try:
        return utc_now().timestamp() - path.stat().st_mtime > seconds
    except FileNotFoundError:
        return False
