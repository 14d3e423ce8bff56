"""Accepting submissions: validate the finished upload, check the quota, queue the evaluation.

Quota rules (checked in one transaction holding the account's row lock, so two
simultaneous requests cannot both pass): one submission in flight per account (also a
partial unique index), and one submission per challenge every ``submission_cooldown_h``
hours, failed ones included. A submission that fails validation is answered with every
problem at once and leaves nothing behind: no upload, no file, no queued job. An
accepted upload's file moves into ``submissions/`` under the upload's id (recorded since
the upload opened), then the submission row is committed: a crash between the two
leaves a file that :func:`semantic3d.server.services.recovery.recover_stored_files`
hands back to its upload at the next start, so no upload is lost and no file orphaned.
"""

from __future__ import annotations

import logging
import os
from datetime import datetime, timedelta
from typing import Any, BinaryIO

from sqlalchemy import func, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, sessionmaker

from semantic3d.core.errors import SubmissionError
from semantic3d.evaluation import MethodInfo, validate_submission
from semantic3d.server.db import lock_user, write_transaction
from semantic3d.server.errors import (
    InvalidInputError,
    NotFoundError,
    ThrottledError,
    UploadIncompleteError,
)
from semantic3d.server.models import (
    JOB_DONE,
    Job,
    Submission,
    UploadSession,
    utc_now,
)
from semantic3d.server.schemas import MethodCard, Progress, SubmissionInfo, SubmissionScores
from semantic3d.server.services.challenges import NOT_INSTALLED, ChallengeCache, get_challenge
from semantic3d.server.services.methods import method_columns, method_of, validate_method
from semantic3d.server.services.scores import result_of, stored_iou
from semantic3d.server.services.upload_files import (
    locked_part,
    part_path,
    stored_name_of,
    sync_folders,
    upload_sha256,
)
from semantic3d.server.services.uploads import delete_upload, owned_upload
from semantic3d.server.settings import Settings

logger = logging.getLogger(__name__)


def check_quota(
    session: Session, settings: Settings, *, user_id: int, challenge_id: int, now: datetime
) -> None:
    """Raise :class:`ThrottledError` if the account may not submit to the challenge now."""
    in_flight = session.scalar(
        select(Submission.id).where(Submission.user_id == user_id, Submission.in_flight).limit(1)
    )
    if in_flight is not None:
        raise ThrottledError(
            f"submission #{in_flight} is still being evaluated: one submission in flight "
            "per account; submit again when it has finished",
            retry_after_s=60,
        )
    next_allowed = next_submission_at(session, settings, user_id=user_id, challenge_id=challenge_id)
    if next_allowed is not None and next_allowed > now:
        raise ThrottledError(
            _cooldown_message(settings, next_allowed),
            retry_after_s=int((next_allowed - now).total_seconds()) + 1,
        )


def next_submission_at(
    session: Session, settings: Settings, *, user_id: int, challenge_id: int
) -> datetime | None:
    """When the cooldown lets the account submit to the challenge again (``None``: no limit)."""
    if settings.submission_cooldown_h <= 0:
        return None
    last = session.scalar(
        select(func.max(Submission.created_at)).where(
            Submission.user_id == user_id, Submission.challenge_id == challenge_id
        )
    )
    return None if last is None else last + timedelta(hours=settings.submission_cooldown_h)


def _cooldown_message(settings: Settings, next_allowed: datetime) -> str:
    return (
        f"one submission per challenge every {settings.submission_cooldown_h:g} h "
        f"(failed ones count): your next one is allowed at {next_allowed:%Y-%m-%d %H:%M} UTC"
    )


def check_upload_allowed(
    factory: sessionmaker[Session], settings: Settings, *, user_id: int, challenge: str
) -> None:
    """Refuse, before any byte is sent, an upload that could never be finalized.

    An upload session lives ``upload_session_ttl_s``; if the account's cooldown on the
    challenge ends later than that, the upload would expire first. A challenge whose
    ground truth is not installed takes no uploads. (One in flight is not
    checked here: that evaluation may well finish while the upload runs.)
    """
    now = utc_now()
    with factory() as session:
        row = get_challenge(session, challenge)
        if not row.ground_truth_installed:
            raise InvalidInputError(f"challenge {challenge!r}: submissions are {NOT_INSTALLED}")
        next_allowed = next_submission_at(session, settings, user_id=user_id, challenge_id=row.id)
    if next_allowed is None:
        return
    start_from = next_allowed - timedelta(seconds=settings.upload_session_ttl_s)
    if start_from > now:
        raise ThrottledError(
            _cooldown_message(settings, next_allowed)
            + f"; an upload started now would expire before then, start it after "
            f"{start_from:%Y-%m-%d %H:%M} UTC",
            retry_after_s=int((start_from - now).total_seconds()) + 1,
        )


def finalize_upload(
    factory: sessionmaker[Session],
    settings: Settings,
    cache: ChallengeCache,
    *,
    user_id: int,
    upload_id: str,
    method: MethodInfo,
) -> Submission:
    """Turn a complete upload into a queued submission (see the module docstring)."""
    method = validate_method(method)
    with factory() as session:
        upload = owned_upload(session, upload_id, user_id)
        challenge_row = upload.challenge
        if not challenge_row.is_open:
            raise InvalidInputError(
                f"challenge {challenge_row.name!r} was closed to new submissions while "
                "you were uploading; nothing was queued"
            )
        check_quota(
            session, settings, user_id=user_id, challenge_id=challenge_row.id, now=utc_now()
        )
    with locked_part(settings, upload_id) as handle:
        return _accept(factory, settings, cache, handle=handle, upload=upload, method=method)


def _accept(
    factory: sessionmaker[Session],
    settings: Settings,
    cache: ChallengeCache,
    *,
    handle: BinaryIO,
    upload: UploadSession,
    method: MethodInfo,
) -> Submission:
    """Check, store and queue a locked upload (``finalize_upload`` holds the part file)."""
    challenge_row, user_id = upload.challenge, upload.user_id
    received = os.fstat(handle.fileno()).st_size
    if received < upload.size_bytes:
        raise UploadIncompleteError(
            f"upload {upload.id}: incomplete, {received} of {upload.size_bytes} bytes "
            f"received; resume from offset {received}"
        )
    digest = upload_sha256(settings, upload.id, upload.size_bytes)
    if upload.sha256 and digest != upload.sha256:
        delete_upload(factory, settings, upload.id)
        raise InvalidInputError(
            f"{upload.filename}: corrupted in transit: expected sha256 {upload.sha256}, "
            f"found {digest}; upload it again"
        )
    path = part_path(settings, upload.id)
    try:
        validate_submission(
            path, challenge=cache.get(challenge_row), limits=settings.submission_limits()
        )
    except SubmissionError as exc:
        delete_upload(factory, settings, upload.id)
        problems = [problem.replace(str(path), upload.filename) for problem in exc.problems]
        raise SubmissionError(problems, source=upload.filename) from None

    # The stored name is the upload's id, which its database row has recorded since the
    # upload was opened: a crash between this rename and the commit below leaves a file
    # that the start-up sweep (services/recovery.py) can give back to its upload.
    stored_name = stored_name_of(upload.id)
    target = settings.submissions_dir / stored_name
    os.fsync(handle.fileno())
    path.rename(target)
    sync_folders(path.parent, target.parent)
    try:
        with write_transaction(factory) as session:
            now = utc_now()
            lock_user(session, user_id)
            check_quota(session, settings, user_id=user_id, challenge_id=challenge_row.id, now=now)
            submission = Submission(
                user_id=user_id,
                challenge_id=challenge_row.id,
                created_at=now,
                in_flight=True,
                **method_columns(method),
                filename=upload.filename,
                stored_name=stored_name,
                size_bytes=upload.size_bytes,
                sha256=digest,
            )
            session.add(submission)
            session.flush()
            session.add(Job(submission_id=submission.id, created_at=now))
            row = session.get(UploadSession, upload.id)
            if row is not None:
                session.delete(row)
    except IntegrityError:
        target.rename(path)
        raise ThrottledError(
            "another submission of yours was accepted a moment ago: one submission in "
            "flight per account",
            retry_after_s=60,
        ) from None
    except BaseException:
        target.rename(path)
        raise
    logger.info(
        "submission #%d queued: %s, %d bytes, sha256 %s",
        submission.id,
        challenge_row.name,
        upload.size_bytes,
        digest[:12],
    )
    return submission


def set_published(
    factory: sessionmaker[Session], *, user_id: int, submission_id: int, published: bool
) -> Submission:
    """Publish (or withdraw) an evaluated submission of the caller's on its leaderboard."""
    with write_transaction(factory) as session:
        submission = session.get(Submission, submission_id)
        if submission is None or submission.user_id != user_id:
            raise NotFoundError(f"submission #{submission_id}: not one of yours")
        if published and (submission.job.status != JOB_DONE or submission.mean_iou is None):
            raise InvalidInputError(
                f"submission #{submission_id}: only evaluated submissions can be published "
                f"(status: {submission.job.status})"
            )
        submission.published = published
        submission.published_at = utc_now() if published else None
    return submission


def visible_submission(
    session: Session, submission_id: int, *, viewer_id: int | None, viewer_is_admin: bool = False
) -> Submission:
    """A submission the viewer may see: published, their own, or any for an admin."""
    submission = session.get(Submission, submission_id)
    if submission is None or not (
        submission.published or viewer_is_admin or submission.user_id == viewer_id
    ):
        raise NotFoundError(f"no submission #{submission_id}")
    return submission


def user_submissions(factory: sessionmaker[Session], user_id: int) -> list[Submission]:
    """The account's submissions, newest first, with job and challenge loaded."""
    with factory() as session:
        rows = list(
            session.scalars(
                select(Submission)
                .where(Submission.user_id == user_id)
                .order_by(Submission.id.desc())
            )
        )
        for row in rows:
            _ = (row.job, row.challenge)
        return rows


def submission_info(
    submission: Submission, *, owner: bool, confusion: bool = False
) -> SubmissionInfo:
    """The API's view of a submission; errors only for its owner, per-scan scores never.

    ``confusion=False`` leaves the confusion matrix out (``null``): the challenge's policy
    (:func:`semantic3d.server.services.challenges.shows_confusion`) decides who sees it.
    """
    job = submission.job
    scores = None
    if submission.mean_iou is not None:
        result = result_of(submission)
        scores = SubmissionScores(
            mean_iou=submission.mean_iou,
            overall_accuracy=submission.overall_accuracy,
            iou=list(stored_iou(submission.iou_json)),
            n_points=result.n_points if result is not None else 0,
            confusion=result.confusion.tolist() if result is not None and confusion else None,
        )
    owner_fields: dict[str, Any] = {}
    if owner:
        owner_fields = {
            "filename": submission.filename,
            "size_bytes": submission.size_bytes,
            "sha256": submission.sha256,
            "error": submission.error,
            "attempts": job.attempts,
        }
    return SubmissionInfo(
        id=submission.id,
        challenge=submission.challenge.name,
        status=job.status,
        progress=Progress(done=job.progress_done, total=job.progress_total),
        created_at=submission.created_at,
        finished_at=submission.finished_at,
        published=submission.published,
        method=MethodCard.from_method(method_of(submission)),
        scores=scores,
        **owner_fields,
    )
