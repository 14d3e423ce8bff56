"""Schema migrations, SQLite WAL mode, the write lock, and settings from the environment."""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext
from sqlalchemy import inspect, text

from semantic3d.server.db import (
    create_db_engine,
    create_session_factory,
    run_migrations,
    write_transaction,
)
from semantic3d.server.models import Base, User
from semantic3d.server.settings import Settings

from .conftest import check_score_migration


@pytest.fixture
def settings(tmp_path: Path) -> Settings:
    return Settings(data_dir=tmp_path / "data")


def test_migrations_match_the_models(settings: Settings) -> None:
    engine = create_db_engine(settings)
    run_migrations(engine)
    with engine.connect() as connection:
        assert compare_metadata(MigrationContext.configure(connection), Base.metadata) == []
        version = connection.execute(text("SELECT version_num FROM alembic_version")).scalar()
    assert version == "0004"
    assert set(inspect(engine).get_table_names()) >= {"users", "submissions", "jobs"}


def test_upgrading_a_database_with_accounts_keeps_them_usable(settings: Settings) -> None:
    from alembic import command
    from alembic.config import Config

    from semantic3d.server.db import MIGRATIONS_DIR
    from semantic3d.server.services.accounts import authenticate, create_user

    engine = create_db_engine(settings)
    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS_DIR))
    with engine.begin() as connection:
        config.attributes["connection"] = connection
        command.upgrade(config, "0001")
        connection.execute(
            text(
                "INSERT INTO users (username, password_hash, is_admin, created_at, quota_epoch) "
                "VALUES ('old', 'x', 0, '2026-01-01 00:00:00', 0)"
            )
        )
    run_migrations(engine)
    factory = create_session_factory(engine)
    with factory() as session:
        old = session.query(User).filter_by(username="old").one()
        assert old.session_epoch == 0
    create_user(factory, "alice", "correct horse battery")
    user = authenticate(factory, settings, "alice", "correct horse battery", address="a")
    assert user.session_epoch == 0


def test_the_score_migration_goes_both_ways(settings: Settings) -> None:
    check_score_migration(create_db_engine(settings))


def test_migrations_are_idempotent_and_safe_to_run_concurrently(settings: Settings) -> None:
    # Several processes (server, workers, admin commands) may start at once on a new database.
    script = (
        "import sys; from pathlib import Path; "
        "from semantic3d.server.settings import Settings; "
        "from semantic3d.server.db import create_db_engine, run_migrations; "
        "run_migrations(create_db_engine(Settings(data_dir=Path(sys.argv[1]))))"
    )
    processes = [
        subprocess.Popen([sys.executable, "-c", script, str(settings.data_dir)]) for _ in range(3)
    ]
    assert [p.wait(timeout=120) for p in processes] == [0, 0, 0]
    engine = create_db_engine(settings)
    run_migrations(engine)
    with engine.connect() as connection:
        assert connection.execute(text("SELECT count(*) FROM alembic_version")).scalar() == 1


def test_sqlite_runs_in_wal_mode(settings: Settings) -> None:
    engine = create_db_engine(settings)
    with engine.connect() as connection:
        assert connection.exec_driver_sql("PRAGMA journal_mode").scalar() == "wal"
        assert connection.exec_driver_sql("PRAGMA foreign_keys").scalar() == 1
    assert (settings.data_dir / "semantic3d.sqlite3").exists()


def test_write_transactions_take_the_lock_up_front_and_readers_do_not_wait(
    settings: Settings,
) -> None:
    engine = create_db_engine(settings)
    run_migrations(engine)
    factory = create_session_factory(engine)
    holding = threading.Event()
    release = threading.Event()

    def holder() -> None:
        with write_transaction(factory) as session:
            session.execute(text("SELECT 1"))  # a read only, yet the write lock is held
            holding.set()
            release.wait(5)
            session.add(User(username="first", password_hash="x"))

    thread = threading.Thread(target=holder)
    thread.start()
    assert holding.wait(5)
    start = time.monotonic()
    with factory() as session:  # a plain reader is not blocked
        session.execute(text("SELECT count(*) FROM users")).scalar()
    assert time.monotonic() - start < 0.5
    timer = threading.Timer(0.4, release.set)
    timer.start()
    start = time.monotonic()
    with write_transaction(factory) as session:  # a second writer waits for the first
        waited = time.monotonic() - start
        names = [u.username for u in session.query(User)]
        session.add(User(username="second", password_hash="x"))
    thread.join()
    assert waited >= 0.3
    assert names == ["first"]  # and then sees what the first committed


def test_settings_come_from_semantic3d_environment_variables(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("SEMANTIC3D_DATA_DIR", str(tmp_path / "elsewhere"))
    monkeypatch.setenv("SEMANTIC3D_MAX_UPLOAD_BYTES", "12345")
    monkeypatch.setenv("SEMANTIC3D_SUBMISSION_COOLDOWN_H", "24")
    settings = Settings()
    assert settings.data_dir == tmp_path / "elsewhere"
    assert settings.max_upload_bytes == 12345
    assert settings.submission_cooldown_h == 24
    assert settings.is_sqlite and settings.runs_embedded_worker
    pg = Settings(database_url="postgresql+psycopg://u@localhost/db")
    assert not pg.is_sqlite and not pg.runs_embedded_worker


def test_the_session_key_is_generated_once_and_kept(settings: Settings) -> None:
    key = settings.resolved_secret_key()
    assert len(key) >= 40
    assert Settings(data_dir=settings.data_dir).resolved_secret_key() == key
    assert (settings.data_dir / "secret_key").stat().st_mode & 0o777 == 0o600


def test_naive_datetimes_are_refused(settings: Settings) -> None:
    from datetime import datetime

    engine = create_db_engine(settings)
    run_migrations(engine)
    factory = create_session_factory(engine)
    with pytest.raises(Exception, match="naive datetime"), factory() as session:
        session.add(User(username="x1", password_hash="x", created_at=datetime(2020, 1, 1)))
        session.commit()


def test_bad_environment_values_are_one_clear_error(monkeypatch: pytest.MonkeyPatch) -> None:
    from semantic3d.server.settings import SettingsError, load_settings

    monkeypatch.setenv("SEMANTIC3D_MAX_UPLOAD_BYTES", "lots")
    with pytest.raises(SettingsError, match=r"SEMANTIC3D_MAX_UPLOAD_BYTES: .*integer.*'lots'"):
        load_settings()
