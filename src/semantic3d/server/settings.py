"""Server settings, read from ``SEMANTIC3D_*`` environment variables (pydantic-settings).

Everything the server writes lives under :attr:`Settings.data_dir`: the SQLite database
(unless :attr:`Settings.database_url` points at PostgreSQL), the session-signing key,
upload sessions, stored submissions and the hidden ground truth. Nothing under it is
ever served over HTTP.
"""

from __future__ import annotations

import os
import secrets
from pathlib import Path
from typing import Any

from pydantic import Field, ValidationError, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from semantic3d.core.errors import Semantic3DError
from semantic3d.evaluation import SubmissionLimits

GIB = 1 << 30
MIB = 1 << 20


class Settings(BaseSettings):
    """Configuration of one server (and its workers); pass it to ``create_app(settings)``."""

    model_config = SettingsConfigDict(env_prefix="SEMANTIC3D_", extra="forbid", frozen=True)

    data_dir: Path = Field(
        default=Path("semantic3d-data"),
        description="Database, uploads, submissions and hidden ground truth live here.",
    )
    database_url: str | None = Field(
        default=None,
        description="SQLAlchemy URL, e.g. postgresql+psycopg://user@host/db; "
        "default: SQLite (WAL mode) at DATA_DIR/semantic3d.sqlite3.",
    )
    secret_key: str | None = Field(
        default=None,
        description="Signs session cookies; default: generated once into DATA_DIR/secret_key.",
    )
    site_title: str = "semantic3D benchmark"
    registration_open: bool = True
    cookie_secure: bool = Field(
        default=False, description="Send the session cookie over HTTPS only (set behind TLS)."
    )
    session_max_age_s: int = 14 * 24 * 3600

    max_upload_bytes: int = Field(default=8 * GIB, gt=0, description="Largest submission zip.")
    max_chunk_bytes: int = Field(default=512 * MIB, gt=0, description="Largest single PUT.")
    max_open_uploads: int = Field(default=3, ge=1, description="Unfinished uploads per account.")
    upload_session_ttl_s: int = Field(default=48 * 3600, gt=0)
    submission_cooldown_h: float = Field(
        default=72.0, ge=0, description="Hours between two submissions to a challenge."
    )

    min_free_bytes: int = Field(
        default=512 * MIB,
        ge=0,
        description="Free disk space kept on the data folder: bytes that would eat into it "
        "are refused (507) before they are received, so the database can always write.",
    )
    upload_read_timeout_s: float = Field(
        default=60.0, gt=0, description="A PUT whose body stalls this long is cut off (408)."
    )
    max_rejected_uploads: int = Field(
        default=10, ge=1, description="Invalid submissions per account per window, then 429."
    )
    rejected_upload_window_s: int = Field(default=3600, gt=0)

    max_header_bytes: int = Field(
        default=64 << 10,
        ge=1024,
        description="Largest request line and headers, together; more is answered 431.",
    )
    header_timeout_s: float = Field(
        default=10.0,
        gt=0,
        description="A request line and headers must arrive within this, else the "
        "connection is closed (408).",
    )
    max_connections: int = Field(
        default=1000,
        ge=1,
        description="Open connections at most (also kept under the open-file limit); a new "
        "one over the cap closes the one that has waited longest for its request.",
    )
    proxy_headers: bool = Field(
        default=False,
        description="Behind a reverse proxy: take the client address from X-Forwarded-For "
        "(and the scheme from X-Forwarded-Proto) on connections from FORWARDED_ALLOW_IPS.",
    )
    forwarded_allow_ips: str = Field(
        default="127.0.0.1,::1",
        description="The proxy's addresses or networks, comma-separated: the only peers "
        "whose X-Forwarded-* headers are believed.",
    )

    max_member_bytes: int = Field(
        default=4 * GIB, gt=0, description="Largest label file inside a zip, once inflated."
    )
    max_inflated_bytes: int = Field(
        default=32 * GIB, gt=0, description="Largest submission once inflated."
    )

    embedded_worker: bool | None = Field(
        default=None,
        description="Run the evaluation worker in the server process; default: yes on SQLite.",
    )
    job_lease_s: float = Field(default=60.0, gt=0, description="A worker's lease on a job.")
    job_time_limit_s: float = Field(default=6 * 3600.0, gt=0)
    job_max_attempts: int = Field(default=3, ge=1)
    worker_poll_s: float = Field(default=2.0, gt=0)
    evaluation_threads: int | None = Field(
        default=None,
        ge=1,
        description="Threads an evaluation may use; default all cores but one (at least "
        "one), so an evaluation never takes the core the web server answers on.",
    )

    login_max_failures: int = Field(
        default=5, ge=1, description="Failed logins per account from one client address."
    )
    login_max_failures_per_ip: int = Field(
        default=30, ge=1, description="Failed logins per client address, all accounts."
    )
    login_max_failures_per_account: int = Field(
        default=100, ge=1, description="Failed logins per account, all addresses."
    )
    login_window_s: int = Field(default=15 * 60, gt=0)
    register_max_per_ip: int = Field(
        default=10, ge=1, description="Registration attempts per client address per window."
    )
    register_window_s: int = Field(default=3600, gt=0)
    password_hash_concurrency: int = Field(
        default=2, ge=1, description="Password hashes computed at once (argon2: 64 MiB each)."
    )
    password_hash_wait_s: float = Field(
        default=10.0, gt=0, description="Longest wait for a hashing slot, then 503."
    )
    sqlite_busy_timeout_s: float = Field(
        default=60.0, gt=0, description="Wait for SQLite's write lock, then 503."
    )
    postgres_lock_timeout_s: float = Field(
        default=60.0,
        gt=0,
        description="Wait for a PostgreSQL lock (an account's row, a table), then 503.",
    )

    leaderboard_cache_s: float = Field(default=2.0, ge=0)

    @field_validator("forwarded_allow_ips")
    @classmethod
    def _named_proxies(cls, value: str) -> str:
        addresses = [item.strip() for item in value.split(",") if item.strip()]
        if not addresses:
            raise ValueError("expected the proxy's addresses, comma-separated")
        if "*" in addresses:
            raise ValueError(
                "expected the proxy's addresses: '*' would believe X-Forwarded-For from "
                "anyone, and per-address throttles with it"
            )
        return ",".join(addresses)

    @field_validator("data_dir")
    @classmethod
    def _absolute(cls, value: Path) -> Path:
        return value.expanduser().resolve()

    # Derived paths -------------------------------------------------------------------------
    def submission_limits(self) -> SubmissionLimits:
        """Archive-safety caps handed to validation and evaluation."""
        return SubmissionLimits(
            max_member_bytes=self.max_member_bytes, max_total_bytes=self.max_inflated_bytes
        )

    @property
    def evaluation_thread_budget(self) -> int:
        """``evaluation_threads``, or all cores but one (at least one)."""
        from semantic3d.core.threads import available_cores

        if self.evaluation_threads is not None:
            return self.evaluation_threads
        return max(1, available_cores() - 1)

    @property
    def uploads_dir(self) -> Path:
        """Partial uploads (``<session id>.part``)."""
        return self.data_dir / "uploads"

    @property
    def submissions_dir(self) -> Path:
        """Accepted submission zips, under server-generated names."""
        return self.data_dir / "submissions"

    @property
    def orphaned_dir(self) -> Path:
        """Stored files that no submission or upload names, set aside at start-up."""
        return self.data_dir / "orphaned"

    @property
    def ground_truth_dir(self) -> Path:
        """Hidden ground truth, one folder per challenge."""
        return self.data_dir / "ground-truth"

    @property
    def resolved_database_url(self) -> str:
        """:attr:`database_url`, or the embedded SQLite database under :attr:`data_dir`."""
        if self.database_url:
            return self.database_url
        return f"sqlite:///{self.data_dir / 'semantic3d.sqlite3'}"

    @property
    def is_sqlite(self) -> bool:
        """Whether the database is SQLite (the embedded default)."""
        return self.resolved_database_url.startswith("sqlite")

    @property
    def runs_embedded_worker(self) -> bool:
        """Whether ``serve`` also runs the worker in a background thread."""
        return self.is_sqlite if self.embedded_worker is None else self.embedded_worker

    def prepare_data_dir(self) -> None:
        """Create the data folders, private to the server's user (mode 0700)."""
        folders = (self.data_dir, self.uploads_dir, self.submissions_dir, self.ground_truth_dir)
        for folder in folders:
            folder.mkdir(mode=0o700, parents=True, exist_ok=True)
            try:
                if folder.stat().st_mode & 0o077:
                    folder.chmod(0o700)
            except OSError:  # not ours to change (a shared mount): leave it
                pass

    def resolved_secret_key(self) -> str:
        """:attr:`secret_key`, or the key stored in ``DATA_DIR/secret_key`` (created once)."""
        if self.secret_key:
            return self.secret_key
        self.prepare_data_dir()
        path = self.data_dir / "secret_key"
        if not path.exists():
            # Write then hard-link: atomic, and a concurrent process never reads a half file.
            tmp = path.with_name(f"secret_key.{os.getpid()}.tmp")
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
            with os.fdopen(fd, "w", encoding="ascii") as handle:
                handle.write(secrets.token_urlsafe(48))
            try:
                os.link(tmp, path)
            except FileExistsError:
                pass
            finally:
                tmp.unlink()
        return path.read_text(encoding="ascii").strip()


class SettingsError(Semantic3DError, ValueError):
    """A ``SEMANTIC3D_*`` setting has a value of the wrong kind."""


def load_settings(**overrides: Any) -> Settings:
    """:class:`Settings` from the environment and ``overrides``, or :class:`SettingsError`.

    The error names every bad variable: ``SEMANTIC3D_MAX_UPLOAD_BYTES: expected an
    integer, found 'abc'``.
    """
    try:
        return Settings(**overrides)
    except ValidationError as exc:
        problems = []
        for error in exc.errors():
            field = ".".join(str(part) for part in error.get("loc", ())) or "settings"
            name = f"SEMANTIC3D_{field.upper()}" if field in Settings.model_fields else field
            found = error.get("input")
            problems.append(f"{name}: {error.get('msg', 'invalid').lower()}, found {found!r}")
        raise SettingsError("invalid server settings: " + "; ".join(problems)) from None
