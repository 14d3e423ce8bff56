"""Start-up repair of stored files: a file in ``submissions/`` that no submission names.

Finalizing moves an upload's file to ``submissions/<upload id>.zip``, then commits the
submission row (:mod:`.submissions`). A crash between the two (a killed process, a power
cut) leaves a file that no row names, and an upload session whose bytes are gone. At
start-up each such file is

- left alone while a finalize holds its lock (``flock``: another server process is in
  that very gap right now, and its commit or roll-back decides);
- given back to its upload (``uploads/<id>.part``) when the upload session still exists:
  the upload is complete again, and finalizing it again queues it;
- otherwise (the session was deleted or expired meanwhile, or the file predates stored
  names that are upload ids) moved to ``orphaned/`` and logged. Never deleted: a data
  folder opened with the wrong database must not lose its stored submissions.
"""

from __future__ import annotations

import fcntl
import logging
import os
import re
from dataclasses import dataclass
from pathlib import Path

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from semantic3d.server.models import Submission, UploadSession
from semantic3d.server.services.upload_files import part_path, sync_folders
from semantic3d.server.settings import Settings

logger = logging.getLogger(__name__)

_UPLOAD_FILE = re.compile(r"^([0-9a-f]{32})\.zip$")


@dataclass(frozen=True, slots=True)
class RecoveredFiles:
    """What :func:`recover_stored_files` did: upload ids given back, file names set aside."""

    restored: tuple[str, ...] = ()
    set_aside: tuple[str, ...] = ()


def recover_stored_files(factory: sessionmaker[Session], settings: Settings) -> RecoveredFiles:
    """Give interrupted finalizes' files back to their uploads (see the module docstring)."""
    folder = settings.submissions_dir
    if not folder.is_dir():
        return RecoveredFiles()
    names = sorted(path.name for path in folder.iterdir() if path.is_file())
    if not names:
        return RecoveredFiles()
    with factory() as session:
        named = set(session.scalars(select(Submission.stored_name)))
    restored: list[str] = []
    set_aside: list[str] = []
    for name in names:
        if name in named:
            continue
        outcome = _recover(factory, settings, folder / name)
        if outcome == "restored":
            restored.append(name.removesuffix(".zip"))
        elif outcome == "set aside":
            set_aside.append(name)
    return RecoveredFiles(tuple(restored), tuple(set_aside))


def _recover(factory: sessionmaker[Session], settings: Settings, path: Path) -> str | None:
    try:
        handle = path.open("rb")
    except FileNotFoundError:
        return None
    with handle:
        try:
            fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return None  # a finalize holds it: its commit or roll-back decides
        try:
            if not os.path.samestat(os.fstat(handle.fileno()), path.stat()):
                return None  # rolled back to its upload while we waited
        except FileNotFoundError:
            return None
        match = _UPLOAD_FILE.match(path.name)
        upload_id = match.group(1) if match else None
        with factory() as session:
            named = session.scalar(
                select(Submission.id).where(Submission.stored_name == path.name).limit(1)
            )
            if named is not None:
                return None  # committed while we looked
            upload = session.get(UploadSession, upload_id) if upload_id else None
        if upload_id is not None and upload is not None:
            target = part_path(settings, upload_id)
            if not target.exists():
                path.rename(target)
                sync_folders(path.parent, target.parent)
                logger.warning(
                    "upload %s: its finalize was interrupted before the submission was "
                    "recorded; the upload is complete again and can be finalized again",
                    upload_id,
                )
                return "restored"
        orphans = settings.orphaned_dir
        orphans.mkdir(mode=0o700, exist_ok=True)
        target = orphans / path.name
        number = 1
        while target.exists():
            number += 1
            target = orphans / f"{path.name}.{number}"
        path.rename(target)
        sync_folders(path.parent, orphans)
        logger.warning(
            "%s: a stored file that no submission or upload names (an interrupted finalize "
            "whose upload is gone); moved to %s, delete it once checked",
            path.name,
            target,
        )
        return "set aside"
