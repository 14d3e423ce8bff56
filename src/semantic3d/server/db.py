"""Engine, sessions, write locks and migrations.

SQLite (the embedded default) runs in WAL mode so readers never wait for the writer.
Its driver's implicit transactions are replaced by explicit ``BEGIN`` statements so
that a *locking* transaction can start with ``BEGIN IMMEDIATE``: the write lock is
taken before the first read, which is what makes check-then-insert quota rules
race-free. On PostgreSQL the same functions take a row lock (``SELECT ... FOR UPDATE``).
"""

from __future__ import annotations

import logging
import os
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from sqlalchemy import Engine, create_engine, event, make_url, select, text
from sqlalchemy.engine import Connection
from sqlalchemy.exc import OperationalError
from sqlalchemy.orm import Session, sessionmaker
from sqlalchemy.pool import ConnectionPoolEntry

from semantic3d.server.errors import (
    InsufficientStorageError,
    ServerError,
    ServiceUnavailableError,
)
from semantic3d.server.models import User
from semantic3d.server.settings import Settings

logger = logging.getLogger(__name__)

MIGRATIONS_DIR = Path(__file__).parent / "migrations"
_IMMEDIATE = "semantic3d_immediate"
# Alembic keeps its migration context in module globals: one migration per process at a time.
_MIGRATION_LOCK = threading.Lock()
MIGRATION_LOCK_KEY = 0x53336D69
"""PostgreSQL's advisory lock key under which concurrent starters migrate one at a time."""


def create_db_engine(settings: Settings) -> Engine:
    """An engine for ``settings``' database; SQLite gets WAL mode and explicit BEGINs."""
    url = settings.resolved_database_url
    if url.startswith("sqlite"):
        settings.prepare_data_dir()
        _create_private_file(make_url(url).database)
        timeout_s = settings.sqlite_busy_timeout_s
        engine = create_engine(
            url,
            connect_args={"check_same_thread": False, "timeout": timeout_s},
            pool_size=20,
            max_overflow=20,
        )
        _configure_sqlite(engine, busy_timeout_ms=int(timeout_s * 1000))
    else:
        engine = create_engine(
            url,
            connect_args=_postgres_options(url, lock_timeout_s=settings.postgres_lock_timeout_s),
            pool_size=10,
            max_overflow=20,
            pool_pre_ping=True,
        )
    return engine


def _postgres_options(url: str, *, lock_timeout_s: float) -> dict[str, str]:
    """libpq ``options`` bounding every statement's wait for a lock (PostgreSQL waits for
    ever by default), after any options the URL carries; migrations lift the bound."""
    if not url.startswith("postgresql"):
        return {}
    given = make_url(url).query.get("options", "")
    if isinstance(given, tuple):
        given = " ".join(given)
    bound = f"-c lock_timeout={max(1, round(lock_timeout_s * 1000))}"
    return {"options": f"{given} {bound}".strip()}


def _create_private_file(database: str | None) -> None:
    """Create the SQLite file readable by its owner only (its WAL files inherit the mode)."""
    if not database or database == ":memory:" or database.startswith("file:"):
        return
    path = Path(database)
    try:
        os.close(os.open(path, os.O_WRONLY | os.O_CREAT, 0o600))
        if path.stat().st_mode & 0o077:
            path.chmod(0o600)
    except OSError:  # a read-only or foreign file: SQLite itself will say what is wrong
        logger.warning("could not make %s private (mode 0600)", path)


def _configure_sqlite(engine: Engine, *, busy_timeout_ms: int) -> None:
    @event.listens_for(engine, "connect")
    def _on_connect(dbapi_connection: Any, record: ConnectionPoolEntry) -> None:
        # Take transaction control away from the driver: we emit BEGIN ourselves.
        dbapi_connection.isolation_level = None
        cursor = dbapi_connection.cursor()
        cursor.execute("PRAGMA journal_mode=WAL")
        cursor.execute("PRAGMA synchronous=FULL")
        cursor.execute("PRAGMA foreign_keys=ON")
        cursor.execute(f"PRAGMA busy_timeout={busy_timeout_ms}")
        cursor.close()

    @event.listens_for(engine, "begin")
    def _on_begin(connection: Connection) -> None:
        immediate = connection.get_execution_options().get(_IMMEDIATE, False)
        connection.exec_driver_sql("BEGIN IMMEDIATE" if immediate else "BEGIN")


def create_session_factory(engine: Engine) -> sessionmaker[Session]:
    """Sessions that keep loaded attributes after commit (pages render after the commit)."""
    return sessionmaker(engine, expire_on_commit=False)


@contextmanager
def write_transaction(factory: sessionmaker[Session]) -> Iterator[Session]:
    """A session whose transaction holds the database write lock from its first statement.

    On SQLite this is ``BEGIN IMMEDIATE`` (one writer at a time, readers unaffected);
    elsewhere an ordinary transaction in which callers take row locks with
    :func:`lock_user`. Commits on success, rolls back on error.
    """
    with factory() as session:
        try:
            session.connection(execution_options={_IMMEDIATE: True})
            yield session
            session.commit()
        except OperationalError as exc:
            session.rollback()
            raise database_error(exc) from exc
        except BaseException:
            session.rollback()
            raise


def database_error(exc: OperationalError) -> ServerError | OperationalError:
    """A locked or full database as the error to answer with (503, 507), else ``exc``.

    SQLite answers "database is locked" once its busy timeout has passed, PostgreSQL
    "lock timeout" (SQLSTATE 55P03) once its ``lock_timeout`` has, and SQLite "database or
    disk is full" when its disk is; all pass by themselves, so the client is told to come
    back rather than shown an internal error.
    """
    message = str(exc.orig if exc.orig is not None else exc).lower()
    lock_not_available = getattr(exc.orig, "sqlstate", None) == "55P03"  # PostgreSQL
    if "locked" in message or "busy" in message or lock_not_available:
        return ServiceUnavailableError(
            "the database is busy; try again in a few seconds", retry_after_s=5
        )
    if "disk is full" in message or "no space left" in message:
        return InsufficientStorageError(
            "the server's disk is full; nothing was changed, try again later"
        )
    return exc


def lock_user(session: Session, user_id: int) -> User:
    """Lock the account row for the rest of the transaction and bump its quota epoch.

    Two transactions that both call this for one account run one after the other; the
    second sees everything the first committed (PostgreSQL re-reads the row after the
    lock; SQLite's ``BEGIN IMMEDIATE`` already serialised them).
    """
    user = session.execute(
        select(User)
        .where(User.id == user_id)
        .with_for_update()
        .execution_options(populate_existing=True)
    ).scalar_one()
    user.quota_epoch = user.quota_epoch + 1
    session.flush()
    return user


def run_migrations(engine: Engine) -> None:
    """Upgrade the schema to the newest Alembic revision.

    Safe to call from several processes at once: the whole upgrade is one transaction,
    which SQLite serialises with ``BEGIN IMMEDIATE`` and PostgreSQL with an advisory lock
    (see ``migrations/env.py``); the next starter then finds the newest revision.
    """
    from alembic import command
    from alembic.config import Config

    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS_DIR))
    with _MIGRATION_LOCK, engine.connect() as connection:
        if engine.dialect.name == "sqlite":
            connection = connection.execution_options(**{_IMMEDIATE: True})
        # One transaction for every step: Alembic on SQLite would commit after each one,
        # and a starter that had read the old revision could then repeat a step another
        # had just applied. Here the second starter waits for the whole upgrade.
        with connection.begin():
            config.attributes["connection"] = connection
            command.upgrade(config, "head")
    logger.info("database schema at the newest revision")


def ping(engine: Engine) -> None:
    """Raise if the database cannot answer a trivial query."""
    with engine.connect() as connection:
        connection.execute(text("SELECT 1"))
