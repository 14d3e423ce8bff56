"""A ready-to-browse server for ``semantic3d demo --serve``: one challenge, one result.

The demo's ground truth becomes a custom challenge, its predictions a submission that
goes through the ordinary path (upload, validation, queue, the worker's
``evaluate_submission``) and is published, so the page shows what a participant sees.
"""

from __future__ import annotations

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


def zip_predictions(folder: Path, target: Path) -> Path:
    """Zip every ``*.labels`` file of ``folder`` (flat) into ``target``."""
    with zipfile.ZipFile(target, "w", zipfile.ZIP_DEFLATED, compresslevel=6) as archive:
        for path in sorted(folder.glob("*.labels")):
            archive.write(path, path.name)
    return target


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
    archive = zip_predictions(predictions, settings.data_dir / "demo-predictions.zip")
    try:
        submission = import_submission(
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
    Worker(settings, factory, cache=cache).run_once()
    with factory() as session:
        evaluated = session.get_one(Submission, submission.id)
        mean_iou = evaluated.mean_iou
    if mean_iou is not None:
        set_published(factory, user_id=user.id, submission_id=submission.id, published=True)
    logger.info("demo submission #%d evaluated: mIoU %s", submission.id, mean_iou)
    return DemoServer(submission.id, mean_iou, password, token)
