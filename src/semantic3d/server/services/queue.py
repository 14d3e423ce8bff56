"""A database-backed job queue with leases.

A worker *leases* a job for ``job_lease_s`` seconds and renews the lease with heartbeats
while it evaluates. A worker that dies stops renewing; once its lease has expired any
worker may lease the job again (another attempt). Every state change after the lease is
*fenced*: it only applies while ``(leased_by, attempts)`` still match the lease, so a
worker that lost its lease cannot overwrite the work of the one that took over. The
sweeper fails jobs past ``job_max_attempts`` or ``job_time_limit_s``. All statements are
portable compare-and-set updates (SQLite and PostgreSQL alike).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import Any

from sqlalchemy import and_, func, or_, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, sessionmaker

from semantic3d.server.db import write_transaction
from semantic3d.server.errors import ConflictError, NotFoundError
from semantic3d.server.models import (
    JOB_DONE,
    JOB_FAILED,
    JOB_QUEUED,
    JOB_RUNNING,
    Job,
    Submission,
    utc_now,
)
from semantic3d.server.services.scores import StoredScores
from semantic3d.server.settings import Settings

logger = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class Lease:
    """A worker's claim on one job; ``attempt`` fences stale workers out."""

    job_id: int
    submission_id: int
    worker_id: str
    attempt: int


@dataclass(frozen=True, slots=True)
class SweepReport:
    """What one sweep did."""

    failed_attempts: int
    failed_time_limit: int


def _rowcount(result: Any) -> int:
    """Rows changed by an UPDATE (``CursorResult.rowcount``)."""
    count: int = result.rowcount
    return count


def _leasable(now: datetime, max_attempts: int) -> Any:
    return and_(
        or_(
            Job.status == JOB_QUEUED,
            and_(Job.status == JOB_RUNNING, Job.leased_until < now),
        ),
        Job.attempts < max_attempts,
    )


def lease_next(factory: sessionmaker[Session], settings: Settings, worker_id: str) -> Lease | None:
    """Lease the oldest queued (or abandoned) job, or ``None`` if there is none."""
    now = utc_now()
    with factory() as session:
        candidates = list(
            session.scalars(
                select(Job.id)
                .where(_leasable(now, settings.job_max_attempts))
                .order_by(Job.id)
                .limit(8)
            )
        )
    for job_id in candidates:
        with write_transaction(factory) as session:
            claimed = session.execute(
                update(Job)
                .where(Job.id == job_id, _leasable(now, settings.job_max_attempts))
                .values(
                    status=JOB_RUNNING,
                    leased_by=worker_id,
                    leased_until=now + timedelta(seconds=settings.job_lease_s),
                    heartbeat_at=now,
                    attempts=Job.attempts + 1,
                )
                .execution_options(synchronize_session=False)
            )
            if _rowcount(claimed) != 1:
                continue  # another worker was faster
            session.execute(
                update(Job)
                .where(Job.id == job_id, Job.started_at.is_(None))
                .values(started_at=now)
                .execution_options(synchronize_session=False)
            )
            job = session.execute(
                select(Job.submission_id, Job.attempts).where(Job.id == job_id)
            ).one()
        logger.info("%s leased job %d (attempt %d)", worker_id, job_id, job.attempts)
        return Lease(job_id, job.submission_id, worker_id, job.attempts)
    return None


def _fenced(lease: Lease) -> Any:
    return and_(
        Job.id == lease.job_id,
        Job.status == JOB_RUNNING,
        Job.leased_by == lease.worker_id,
        Job.attempts == lease.attempt,
    )


def renew(
    factory: sessionmaker[Session], settings: Settings, lease: Lease, *, done: int, total: int
) -> bool:
    """Heartbeat: extend the lease and record progress; ``False`` if the lease is lost."""
    now = utc_now()
    with write_transaction(factory) as session:
        result = session.execute(
            update(Job)
            .where(_fenced(lease))
            .values(
                leased_until=now + timedelta(seconds=settings.job_lease_s),
                heartbeat_at=now,
                progress_done=done,
                progress_total=total,
            )
            .execution_options(synchronize_session=False)
        )
        return _rowcount(result) == 1


def release(factory: sessionmaker[Session], lease: Lease) -> bool:
    """Give a job back unfinished (worker shutting down); the attempt is not counted."""
    with write_transaction(factory) as session:
        result = session.execute(
            update(Job)
            .where(_fenced(lease))
            .values(
                status=JOB_QUEUED,
                leased_by=None,
                leased_until=None,
                attempts=Job.attempts - 1,
                progress_done=0,
            )
            .execution_options(synchronize_session=False)
        )
        return _rowcount(result) == 1


def complete(
    factory: sessionmaker[Session],
    lease: Lease,
    *,
    scores: StoredScores,
    progress_total: int,
) -> bool:
    """Record a finished evaluation; ``False`` (nothing written) if the lease was lost.

    ``scores`` comes from :func:`~semantic3d.server.services.scores.stored_scores`.
    """
    now = utc_now()
    with write_transaction(factory) as session:
        finished = session.execute(
            update(Job)
            .where(_fenced(lease))
            .values(
                status=JOB_DONE,
                finished_at=now,
                leased_until=None,
                error=None,
                progress_done=progress_total,
                progress_total=progress_total,
            )
            .execution_options(synchronize_session=False)
        )
        if _rowcount(finished) != 1:
            return False
        session.execute(
            update(Submission)
            .where(Submission.id == lease.submission_id)
            .values(in_flight=False, finished_at=now, error=None, **scores.columns())
            .execution_options(synchronize_session=False)
        )
    logger.info("job %d done by %s", lease.job_id, lease.worker_id)
    return True


def fail(factory: sessionmaker[Session], lease: Lease, error: str) -> bool:
    """Record a failed evaluation (counts toward the quota); ``False`` if the lease was lost."""
    now = utc_now()
    with write_transaction(factory) as session:
        failed = session.execute(
            update(Job)
            .where(_fenced(lease))
            .values(status=JOB_FAILED, finished_at=now, leased_until=None, error=error)
            .execution_options(synchronize_session=False)
        )
        if _rowcount(failed) != 1:
            return False
        _fail_submission(session, lease.submission_id, error, now)
    logger.info("job %d failed: %s", lease.job_id, error.splitlines()[0] if error else "")
    return True


def _fail_submission(session: Session, submission_id: int, error: str, now: datetime) -> None:
    session.execute(
        update(Submission)
        .where(Submission.id == submission_id)
        .values(in_flight=False, finished_at=now, error=error)
        .execution_options(synchronize_session=False)
    )


def sweep(factory: sessionmaker[Session], settings: Settings) -> SweepReport:
    """Fail jobs whose workers died too often or that ran past the time limit."""
    now = utc_now()
    too_old = now - timedelta(seconds=settings.job_time_limit_s)
    counts = {"attempts": 0, "time": 0}
    with write_transaction(factory) as session:
        stuck = session.execute(
            select(Job.id, Job.submission_id, Job.attempts, Job.started_at).where(
                Job.status.in_((JOB_RUNNING, JOB_QUEUED)),
                or_(
                    and_(
                        Job.attempts >= settings.job_max_attempts,
                        or_(Job.status == JOB_QUEUED, Job.leased_until < now),
                    ),
                    Job.started_at < too_old,
                ),
            )
        ).all()
        for job_id, submission_id, attempts, started_at in stuck:
            if started_at is not None and started_at < too_old:
                limit_h = settings.job_time_limit_s / 3600
                error = f"evaluation did not finish within the time limit ({limit_h:g} h)"
                counts["time"] += 1
            else:
                error = f"evaluation abandoned: its worker stopped {attempts} times"
                counts["attempts"] += 1
            session.execute(
                update(Job)
                .where(Job.id == job_id)
                .values(status=JOB_FAILED, finished_at=now, leased_until=None, error=error)
                .execution_options(synchronize_session=False)
            )
            _fail_submission(session, submission_id, error, now)
            logger.warning("job %d failed by the sweeper: %s", job_id, error)
    return SweepReport(failed_attempts=counts["attempts"], failed_time_limit=counts["time"])


def requeue(factory: sessionmaker[Session], submission_id: int) -> None:
    """Admin: evaluate a submission again from scratch (it counts as in flight again)."""
    try:
        with write_transaction(factory) as session:
            job = session.scalars(select(Job).where(Job.submission_id == submission_id)).first()
            if job is None:
                raise NotFoundError(f"no submission #{submission_id}")
            if job.status in (JOB_QUEUED, JOB_RUNNING):
                raise ConflictError(f"submission #{submission_id} is already {job.status}")
            job.status = JOB_QUEUED
            job.attempts = 0
            job.leased_by = None
            job.leased_until = None
            job.started_at = None
            job.finished_at = None
            job.error = None
            job.progress_done = 0
            job.submission.in_flight = True
            job.submission.error = None
    except IntegrityError:
        raise ConflictError(
            f"submission #{submission_id}: its account has another submission in flight; "
            "requeue it when that one has finished"
        ) from None


def queue_counts(factory: sessionmaker[Session]) -> dict[str, int]:
    """Number of jobs per state (admin page)."""
    with factory() as session:
        rows = session.execute(select(Job.status, func.count()).group_by(Job.status)).all()
    return {status: count for status, count in rows}
