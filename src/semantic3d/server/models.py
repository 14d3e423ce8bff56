"""Database tables (SQLAlchemy 2 declarative models).

The schema is created and upgraded by the Alembic migrations in ``migrations/``; a test
checks that these models and the migrations agree. Times are stored as naive UTC and
returned as aware UTC (:class:`UTCDateTime`), so SQL comparisons work the same on SQLite
and PostgreSQL.
"""

from __future__ import annotations

from datetime import UTC, datetime

from sqlalchemy import (
    BigInteger,
    Boolean,
    DateTime,
    Float,
    ForeignKey,
    Index,
    Integer,
    MetaData,
    String,
    Text,
    text,
    true,
)
from sqlalchemy.engine import Dialect
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, relationship
from sqlalchemy.types import TypeDecorator

# Deterministic constraint names, so migrations can refer to them on every database.
NAMING_CONVENTION = {
    "ix": "ix_%(column_0_label)s",
    "uq": "uq_%(table_name)s_%(column_0_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}


def utc_now() -> datetime:
    """The current time, timezone-aware UTC."""
    return datetime.now(UTC)


class UTCDateTime(TypeDecorator[datetime]):
    """A timestamp stored as naive UTC and read back as aware UTC."""

    impl = DateTime
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        if value.tzinfo is None:
            raise ValueError(f"naive datetime {value!r}: expected a timezone-aware UTC time")
        return value.astimezone(UTC).replace(tzinfo=None)

    def process_result_value(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        return None if value is None else value.replace(tzinfo=UTC)


class Base(DeclarativeBase):
    """Declarative base with the naming convention."""

    metadata = MetaData(naming_convention=NAMING_CONVENTION)


class User(Base):
    """An account; ``username`` is stored lower-case."""

    __tablename__ = "users"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    username: Mapped[str] = mapped_column(String(64), unique=True)
    password_hash: Mapped[str] = mapped_column(String(255))
    is_admin: Mapped[bool] = mapped_column(Boolean, default=False)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utc_now)
    # Bumped under a row lock by every quota-checked action: serialises them per account.
    quota_epoch: Mapped[int] = mapped_column(Integer, default=0)
    # Part of every session cookie's check; bumped at logout, ending the account's sessions
    # (a signed cookie copied before the logout is refused from then on).
    session_epoch: Mapped[int] = mapped_column(Integer, default=0, server_default="0")


class ApiToken(Base):
    """A CLI token: only the sha256 of the secret is stored; the secret is shown once."""

    __tablename__ = "api_tokens"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    user_id: Mapped[int] = mapped_column(ForeignKey("users.id", ondelete="CASCADE"), index=True)
    name: Mapped[str] = mapped_column(String(100))
    token_hash: Mapped[str] = mapped_column(String(64), unique=True)
    prefix: Mapped[str] = mapped_column(String(16))
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utc_now)
    last_used_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)
    revoked_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)

    user: Mapped[User] = relationship()


class LoginFailure(Base):
    """One failed login; recent rows per account and per address throttle logins."""

    __tablename__ = "login_failures"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    username: Mapped[str] = mapped_column(String(64), index=True)
    address: Mapped[str] = mapped_column(String(64), index=True)
    at: Mapped[datetime] = mapped_column(UTCDateTime, default=utc_now, index=True)


class ChallengeRecord(Base):
    """A hosted challenge (its table row); its hidden ground truth lives in
    ``DATA_DIR/ground-truth/<name>``. The evaluation protocol's challenge (scans, names,
    point counts) is :class:`semantic3d.evaluation.Challenge`, built from this row by
    :func:`semantic3d.server.services.challenges.build_challenge`.
    """

    __tablename__ = "challenges"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    name: Mapped[str] = mapped_column(String(64), unique=True)
    kind: Mapped[str] = mapped_column(String(16))  # "semantic-8", "reduced-8" or "custom"
    title: Mapped[str] = mapped_column(String(200))
    description: Mapped[str] = mapped_column(Text, default="")
    protocol_version: Mapped[str] = mapped_column(String(32), default="")
    n_scans: Mapped[int] = mapped_column(Integer)
    n_points: Mapped[int | None] = mapped_column(BigInteger, nullable=True)
    # {submission file name: number of points}, counted once when the challenge is installed.
    scan_points_json: Mapped[str] = mapped_column(Text, default="{}")
    is_open: Mapped[bool] = mapped_column(Boolean, default=True)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utc_now)
    # False for the benchmark's own challenges until an administrator installs their hidden
    # ground truth: listed (with the paper's reference results) but closed to submissions.
    ground_truth_installed: Mapped[bool] = mapped_column(
        Boolean, default=True, server_default=true()
    )
    # Whether participants see the confusion matrix: None follows the scan-count rule of
    # :func:`semantic3d.server.services.challenges.shows_confusion`, True/False overrides it.
    show_confusion: Mapped[bool | None] = mapped_column(Boolean, nullable=True)


class UploadSession(Base):
    """A resumable upload; bytes received so far are the size of ``<id>.part`` on disk."""

    __tablename__ = "upload_sessions"

    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    user_id: Mapped[int] = mapped_column(ForeignKey("users.id", ondelete="CASCADE"), index=True)
    challenge_id: Mapped[int] = mapped_column(ForeignKey("challenges.id", ondelete="CASCADE"))
    size_bytes: Mapped[int] = mapped_column(BigInteger)
    sha256: Mapped[str | None] = mapped_column(String(64), nullable=True)
    filename: Mapped[str] = mapped_column(String(255))
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utc_now)
    expires_at: Mapped[datetime] = mapped_column(UTCDateTime, index=True)

    challenge: Mapped[ChallengeRecord] = relationship()


class Submission(Base):
    """An accepted submission: method card, stored zip, and (once evaluated) its scores."""

    __tablename__ = "submissions"
    __table_args__ = (
        # At most one submission in flight per account, enforced by the database itself.
        Index(
            "uq_submissions_one_in_flight",
            "user_id",
            unique=True,
            sqlite_where=text("in_flight = 1"),
            postgresql_where=text("in_flight"),
        ),
        Index("ix_submissions_user_challenge_created", "user_id", "challenge_id", "created_at"),
        Index("ix_submissions_board", "challenge_id", "published", "mean_iou"),
    )

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    user_id: Mapped[int] = mapped_column(ForeignKey("users.id", ondelete="CASCADE"))
    challenge_id: Mapped[int] = mapped_column(ForeignKey("challenges.id", ondelete="CASCADE"))
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utc_now)
    in_flight: Mapped[bool] = mapped_column(Boolean, default=True)

    method_name: Mapped[str] = mapped_column(String(200))
    description: Mapped[str] = mapped_column(Text, default="")
    paper_url: Mapped[str] = mapped_column(String(500), default="")
    code_url: Mapped[str] = mapped_column(String(500), default="")
    runtime_s: Mapped[float | None] = mapped_column(Float, nullable=True)
    hardware: Mapped[str | None] = mapped_column(String(200), nullable=True)

    filename: Mapped[str] = mapped_column(String(255))
    stored_name: Mapped[str] = mapped_column(String(64), unique=True)
    size_bytes: Mapped[int] = mapped_column(BigInteger)
    sha256: Mapped[str] = mapped_column(String(64))

    published: Mapped[bool] = mapped_column(Boolean, default=False)
    published_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)
    finished_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)
    error: Mapped[str | None] = mapped_column(Text, nullable=True)
    # The evaluation result is ``result_json``; the leaderboard query filters and orders by
    # ``mean_iou``/``overall_accuracy`` and lists ``iou_json``, so those repeat parts of it.
    # All four are written together by ``services.scores.stored_scores``.
    mean_iou: Mapped[float | None] = mapped_column(Float, nullable=True)
    overall_accuracy: Mapped[float | None] = mapped_column(Float, nullable=True)
    iou_json: Mapped[str | None] = mapped_column(Text, nullable=True)
    result_json: Mapped[str | None] = mapped_column(Text, nullable=True)

    user: Mapped[User] = relationship()
    challenge: Mapped[ChallengeRecord] = relationship()
    job: Mapped[Job] = relationship(back_populates="submission", uselist=False)


class Job(Base):
    """The evaluation of one submission, leased by one worker at a time."""

    __tablename__ = "jobs"
    __table_args__ = (Index("ix_jobs_status_id", "status", "id"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    submission_id: Mapped[int] = mapped_column(
        ForeignKey("submissions.id", ondelete="CASCADE"), unique=True
    )
    status: Mapped[str] = mapped_column(String(16), default="queued")
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    leased_by: Mapped[str | None] = mapped_column(String(100), nullable=True)
    leased_until: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)
    heartbeat_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utc_now)
    started_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)
    finished_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)
    progress_done: Mapped[int] = mapped_column(BigInteger, default=0)
    progress_total: Mapped[int] = mapped_column(BigInteger, default=0)
    error: Mapped[str | None] = mapped_column(Text, nullable=True)

    submission: Mapped[Submission] = relationship(back_populates="job")


JOB_QUEUED = "queued"
JOB_RUNNING = "running"
JOB_DONE = "done"
JOB_FAILED = "failed"
JOB_STATES = (JOB_QUEUED, JOB_RUNNING, JOB_DONE, JOB_FAILED)
