"""A ready-to-browse server for ``semantic3d demo --serve``: one challenge, one result.

The demo's ground truth becomes a custom challenge, its predictions a submission that
goes through the ordinary path (upload, validation, queue, the worker's
``evaluate_submission``) and is published, so the page shows what a participant sees.

Running the demo again on the same data folder adds nothing for the same predictions:
the zip is built byte for byte the same from the same ``.labels`` files, and a submission
of the demo account with that hash is reused. New predictions make a new submission,
and the demo account's earlier ones are withdrawn from the board (kept, not deleted), so
the board shows the demo's current result once.
"""

from __future__ import annotations

import hashlib
import logging
import secrets
import shutil
import zipfile
from dataclasses import dataclass
from pathlib import Path

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from semantic3d.evaluation import MethodInfo
from semantic3d.server.models import ChallengeRecord, Submission, User
from semantic3d.server.services.accounts import create_token, create_user
from semantic3d.server.services.challenges import ChallengeCache, install_challenge
from semantic3d.server.services.submissions import finalize_upload, set_published
from semantic3d.server.services.upload_files import part_path
from semantic3d.server.services.uploads import create_upload
from semantic3d.server.settings import Settings
from semantic3d.server.worker import Worker

logger = logging.getLogger(__name__)

DEMO_CHALLENGE = "demo"
DEMO_USER = "demo"


@dataclass(frozen=True, slots=True)
class DemoServer:
    """What ``prepare_demo`` set up: the account's credentials (new ones only) and the entry."""

    submission_id: int
    mean_iou: float | None
    password: str | None
    token: str | None


def import_submission(
    factory: sessionmaker[Session],
    settings: Settings,
    cache: ChallengeCache,
    *,
    user_id: int,
    challenge: str,
    path: Path,
    method: MethodInfo,
) -> Submission:
    """Submit a local zip as ``user_id`` through the ordinary checks (admin and demo use)."""
    upload = create_upload(
        factory,
        settings,
        user_id=user_id,
        challenge=challenge,
        size_bytes=path.stat().st_size,
        filename=path.name,
    )
    shutil.copyfile(path, part_path(settings, upload.id))
    return finalize_upload(
        factory, settings, cache, user_id=user_id, upload_id=upload.id, method=method
    )


_ZIP_TIME = (1980, 1, 1, 0, 0, 0)


def zip_predictions(folder: Path, target: Path) -> Path:
    """Zip every ``*.labels`` file of ``folder`` (flat) into ``target``, reproducibly.

    Members are written in name order with a fixed time stamp and mode, so the same
    files always give the same bytes (and the same sha256), whenever they were written.
    """
    with zipfile.ZipFile(target, "w", zipfile.ZIP_DEFLATED, compresslevel=6) as archive:
        for path in sorted(folder.glob("*.labels")):
            info = zipfile.ZipInfo(path.name, date_time=_ZIP_TIME)
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            with path.open("rb") as source, archive.open(info, "w") as member:
                shutil.copyfileobj(source, member, 1 << 20)
    return target


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _same_submission(
    factory: sessionmaker[Session], *, user_id: int, challenge_id: int, sha256: str
) -> Submission | None:
    """The account's evaluated submission of the same zip to the challenge, if any."""
    with factory() as session:
        return session.scalars(
            select(Submission)
            .where(
                Submission.user_id == user_id,
                Submission.challenge_id == challenge_id,
                Submission.sha256 == sha256,
                Submission.mean_iou.is_not(None),
            )
            .order_by(Submission.id.desc())
        ).first()


def _withdraw_others(
    factory: sessionmaker[Session], *, user_id: int, challenge_id: int, keep_id: int
) -> None:
    """Withdraw the account's other published submissions to the challenge from its board."""
    with factory() as session:
        others = session.scalars(
            select(Submission.id).where(
                Submission.user_id == user_id,
                Submission.challenge_id == challenge_id,
                Submission.published,
                Submission.id != keep_id,
            )
        ).all()
    for submission_id in others:
        set_published(factory, user_id=user_id, submission_id=submission_id, published=False)


def prepare_demo(
    factory: sessionmaker[Session],
    settings: Settings,
    *,
    ground_truth: Path,
    predictions: Path,
    method: MethodInfo,
) -> DemoServer:
    """Install the demo challenge, account and published result (idempotent per data dir)."""
    cache = ChallengeCache(settings)
    with factory() as session:
        installed = session.scalars(
            select(ChallengeRecord).where(ChallengeRecord.name == DEMO_CHALLENGE)
        ).first()
        user = session.scalars(select(User).where(User.username == DEMO_USER)).first()
    if installed is None:
        install_challenge(
            factory,
            settings,
            DEMO_CHALLENGE,
            ground_truth,
            title="Demo: simulated terrestrial scan",
            description="The held-out station of `semantic3d demo`, scored by the server.",
            # Simulated data, nothing to hide: show the matrix although it has one scan.
            show_confusion=True,
        )
    password = token = None
    if user is None:
        password = secrets.token_urlsafe(12)
        user = create_user(factory, DEMO_USER, password)
        token = create_token(factory, user.id, "demo")[1]
    with factory() as session:
        challenge_id = session.scalars(
            select(ChallengeRecord.id).where(ChallengeRecord.name == DEMO_CHALLENGE)
        ).one()
    archive = zip_predictions(predictions, settings.data_dir / "demo-predictions.zip")
    try:
        same = _same_submission(
            factory, user_id=user.id, challenge_id=challenge_id, sha256=_sha256(archive)
        )
        submission = same or import_submission(
            factory,
            settings,
            cache,
            user_id=user.id,
            challenge=DEMO_CHALLENGE,
            path=archive,
            method=method,
        )
    finally:
        archive.unlink()
    if same is not None:
        logger.info("demo submission #%d: the same predictions, reused", submission.id)
    else:
        Worker(settings, factory, cache=cache).run_once()
    with factory() as session:
        evaluated = session.get_one(Submission, submission.id)
        mean_iou = evaluated.mean_iou
    if mean_iou is not None:
        set_published(factory, user_id=user.id, submission_id=submission.id, published=True)
        _withdraw_others(factory, user_id=user.id, challenge_id=challenge_id, keep_id=submission.id)
    logger.info("demo submission #%d evaluated: mIoU %s", submission.id, mean_iou)
    return DemoServer(submission.id, mean_iou, password, token)
