"""The PostgreSQL path against a real, throwaway PostgreSQL cluster (initdb + pg_ctl).

Skips when the PostgreSQL server binaries are absent (CI installs the Debian package).
As root (CI), the cluster runs as the ``postgres`` system user, as PostgreSQL requires.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from .conftest import (
    Harness,
    build_harness,
    check_score_migration,
    ground_truth_arrays,
    make_settings,
    noisy_predictions,
    submission_zip,
)
from .processes import free_port

pytestmark = pytest.mark.slow


def _pg_bin(name: str) -> str | None:
    found = shutil.which(name)
    if found:
        return found
    root = Path("/usr/lib/postgresql")  # Debian keeps the server binaries off PATH
    candidates = sorted(root.glob(f"*/bin/{name}"), key=lambda p: int(p.parts[-3].split(".")[0]))
    return str(candidates[-1]) if candidates else None


@pytest.fixture(scope="module")
def postgres_server() -> Iterator[str]:
    """A PostgreSQL cluster on 127.0.0.1:<free port>; yields its base URL."""
    pytest.importorskip("psycopg")
    initdb, pg_ctl = _pg_bin("initdb"), _pg_bin("pg_ctl")
    if initdb is None or pg_ctl is None:
        pytest.skip("PostgreSQL server binaries (initdb, pg_ctl) are not installed")
    prefix: list[str] = []
    root = Path(tempfile.mkdtemp(prefix="semantic3d-pg-"))
    if os.geteuid() == 0:  # PostgreSQL refuses to run as root
        runuser = shutil.which("runuser")
        if runuser is None:
            pytest.skip("running as root without runuser to drop to the postgres user")
        prefix = [runuser, "-u", "postgres", "--"]
        shutil.chown(root, user="postgres")
        root.chmod(0o700)
    data, port = root / "cluster", free_port()

    def run(*args: str) -> None:
        subprocess.run([*prefix, *args], check=True, capture_output=True, timeout=120)

    try:
        run(initdb, "-D", str(data), "-U", "postgres", "--auth=trust", "-E", "UTF8", "--no-sync")
        options = f"-p {port} -k {root} -c listen_addresses=127.0.0.1 -c fsync=off"
        run(pg_ctl, "-D", str(data), "-o", options, "-l", str(root / "log"), "-w", "start")
    except subprocess.CalledProcessError as exc:
        shutil.rmtree(root, ignore_errors=True)
        pytest.fail(f"could not start PostgreSQL: {exc.stderr.decode(errors='replace')}")
    try:
        yield f"postgresql+psycopg://postgres@127.0.0.1:{port}"
    finally:
        subprocess.run([*prefix, pg_ctl, "-D", str(data), "-m", "immediate", "stop"], timeout=60)
        shutil.rmtree(root, ignore_errors=True)


_counter = iter(range(1_000_000))


def _libpq(url: str) -> str:
    """The SQLAlchemy URL ``url`` as psycopg's own connection string."""
    return url.replace("postgresql+psycopg", "postgresql")


@pytest.fixture
def postgres_url(postgres_server: str) -> str:
    """A fresh database on the cluster."""
    import psycopg

    name = f"test_{os.getpid()}_{next(_counter)}"
    dsn = _libpq(postgres_server) + "/postgres"
    with psycopg.connect(dsn, autocommit=True) as connection:
        connection.execute(f'CREATE DATABASE "{name}"')
    return f"{postgres_server}/{name}"


@pytest.fixture
def pg_harness(tmp_path: Path, ground_truth_dir: Path, postgres_url: str) -> Iterator[Harness]:
    settings = make_settings(tmp_path / "data", database_url=postgres_url, max_open_uploads=8)
    yield from build_harness(settings, ground_truth_dir)


def test_migrations_match_the_models_on_postgresql(pg_harness: Harness) -> None:
    from alembic.autogenerate import compare_metadata
    from alembic.migration import MigrationContext

    from semantic3d.server.db import run_migrations
    from semantic3d.server.models import Base

    engine = pg_harness.state.engine
    assert engine.dialect.name == "postgresql"
    run_migrations(engine)  # idempotent
    with engine.connect() as connection:
        assert compare_metadata(MigrationContext.configure(connection), Base.metadata) == []


def test_the_score_migration_goes_both_ways_on_postgresql(
    tmp_path: Path, postgres_url: str
) -> None:
    from semantic3d.server.db import create_db_engine

    engine = create_db_engine(make_settings(tmp_path / "data", database_url=postgres_url))
    try:
        check_score_migration(engine)
    finally:
        engine.dispose()


def test_submission_flow_on_postgresql(pg_harness: Harness) -> None:
    token = pg_harness.user_token("alice")
    headers = {"Authorization": f"Bearer {token}"}
    response = pg_harness.submit(
        token, submission_zip(noisy_predictions(ground_truth_arrays(), 0.9))
    )
    assert response.status_code == 201, response.text
    submission_id = response.json()["id"]
    assert pg_harness.work()
    pg_harness.client.post(
        f"/api/submissions/{submission_id}/publish", json={"published": True}, headers=headers
    )
    entries = pg_harness.client.get("/api/challenges/toy/leaderboard").json()["entries"]
    assert [e["submission_id"] for e in entries] == [submission_id]
    assert 0 < entries[0]["mean_iou"] < 1


@pytest.mark.parametrize("cooldown_h", [0, 72])
def test_quota_is_race_free_on_postgresql(
    tmp_path: Path, ground_truth_dir: Path, postgres_url: str, cooldown_h: float
) -> None:
    from .test_quota import _race

    settings = make_settings(
        tmp_path / "data",
        database_url=postgres_url,
        max_open_uploads=8,
        submission_cooldown_h=cooldown_h,
        upload_session_ttl_s=96 * 3600,  # uploads may start during the cooldown
    )
    harnesses = build_harness(settings, ground_truth_dir)
    pg_harness = next(harnesses)
    try:
        token = pg_harness.user_token("alice")
        for round_index in range(3):
            uploads = [
                pg_harness.upload(
                    token, submission_zip(noisy_predictions(ground_truth_arrays(), 0.9, s))
                )
                for s in range(4)
            ]
            outcomes = _race(pg_harness, uploads, user_id=1)
            expected_ok = 1 if round_index == 0 or cooldown_h == 0 else 0
            assert outcomes.count("ok") == expected_ok, (round_index, outcomes)
            assert pg_harness.work() is (expected_ok == 1)
            for upload_id in uploads:
                pg_harness.client.delete(
                    f"/api/uploads/{upload_id}", headers={"Authorization": f"Bearer {token}"}
                )
    finally:
        harnesses.close()


def test_concurrent_workers_lease_each_job_once_on_postgresql(pg_harness: Harness) -> None:
    from semantic3d.server.services import queue

    for index in range(6):
        token = pg_harness.user_token(f"user{index}")
        assert (
            pg_harness.submit(
                token, submission_zip(noisy_predictions(ground_truth_arrays(), 0.9))
            ).status_code
            == 201
        )
    leased: list[int] = []
    lock = threading.Lock()
    barrier = threading.Barrier(4)

    def grab(worker: str) -> None:
        barrier.wait()
        while (
            lease := queue.lease_next(pg_harness.state.factory, pg_harness.settings, worker)
        ) is not None:
            with lock:
                leased.append(lease.job_id)

    threads = [threading.Thread(target=grab, args=(f"w{i}",)) for i in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert sorted(leased) == sorted(set(leased)) and len(leased) == 6


def test_open_upload_limit_holds_under_concurrency_on_postgresql(pg_harness: Harness) -> None:
    from semantic3d.server.errors import ConflictError
    from semantic3d.server.services.uploads import create_upload

    pg_harness.user_token("alice")
    limit = pg_harness.settings.max_open_uploads
    outcomes: list[str] = []
    barrier = threading.Barrier(limit + 4)

    def create(index: int) -> None:
        barrier.wait()
        try:
            create_upload(
                pg_harness.state.factory,
                pg_harness.settings,
                user_id=1,
                challenge="toy",
                size_bytes=100 + index,
                filename="preds.zip",
            )
            outcomes.append("ok")
        except ConflictError:
            outcomes.append("refused")

    threads = [threading.Thread(target=create, args=(i,)) for i in range(limit + 4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert outcomes.count("ok") == limit and outcomes.count("refused") == 4


def test_login_throttling_on_postgresql(pg_harness: Harness) -> None:
    from semantic3d.server.errors import AuthenticationError, ThrottledError
    from semantic3d.server.services.accounts import authenticate

    pg_harness.user_token("alice")
    outcomes: list[str] = []
    barrier = threading.Barrier(10)

    def guess(index: int) -> None:
        barrier.wait()
        try:
            authenticate(
                pg_harness.state.factory,
                pg_harness.settings,
                "alice",
                f"g{index}",
                address="1.2.3.4",
            )
        except AuthenticationError:
            outcomes.append("wrong")
        except ThrottledError:
            outcomes.append("throttled")

    threads = [threading.Thread(target=guess, args=(i,)) for i in range(10)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert outcomes.count("wrong") <= pg_harness.settings.login_max_failures
    assert len(outcomes) == 10


def test_a_held_account_lock_answers_503_soon_on_postgresql(
    tmp_path: Path, ground_truth_dir: Path, postgres_url: str
) -> None:
    """PostgreSQL waits for a lock for ever by default; the server's requests wait
    ``postgres_lock_timeout_s``, then answer 503 and leave the database as it was."""
    import psycopg

    settings = make_settings(
        tmp_path / "data", database_url=postgres_url, postgres_lock_timeout_s=0.3
    )
    harnesses = build_harness(settings, ground_truth_dir)
    harness = next(harnesses)
    try:
        token = harness.user_token("grace")
        headers = {"Authorization": f"Bearer {token}"}
        body = {"challenge": "toy", "size_bytes": 100}
        with psycopg.connect(_libpq(postgres_url)) as blocker:
            blocker.execute("SET idle_in_transaction_session_timeout = '5s'")  # a bounded test
            blocker.execute("SELECT id FROM users WHERE username = 'grace' FOR UPDATE")
            started = time.perf_counter()
            response = harness.client.post("/api/uploads", json=body, headers=headers)
            elapsed = time.perf_counter() - started
            me = harness.client.get("/api/me", headers=headers)
            with contextlib.suppress(psycopg.OperationalError):  # ended by its own bound
                blocker.rollback()
        assert response.status_code == 503, response.text
        assert response.headers["Retry-After"] == "5"
        assert response.json()["error"] == "the database is busy; try again in a few seconds"
        assert 0.25 < elapsed < 3
        assert me.status_code == 200  # reading needs no lock
        assert harness.client.get("/api/uploads", headers=headers).json()["uploads"] == []
        assert harness.client.post("/api/uploads", json=body, headers=headers).status_code == 201
    finally:
        harnesses.close()


def test_the_lock_bound_keeps_the_url_s_own_options_on_postgresql(
    tmp_path: Path, postgres_url: str
) -> None:
    import psycopg
    from sqlalchemy import text

    from semantic3d.server.db import MIGRATION_LOCK_KEY, create_db_engine, run_migrations

    url = f"{postgres_url}?options=-c%20statement_timeout%3D5000"
    engine = create_db_engine(
        make_settings(tmp_path / "data", database_url=url, postgres_lock_timeout_s=0.3)
    )
    try:
        with psycopg.connect(
            _libpq(postgres_url), autocommit=True
        ) as other:  # another starter, migrating
            other.execute(f"SELECT pg_advisory_lock({MIGRATION_LOCK_KEY})")
            done = threading.Timer(1.0, other.execute, ["SELECT pg_advisory_unlock_all()"])
            done.start()
            started = time.perf_counter()
            run_migrations(engine)  # waits its turn, past the requests' bound
            waited = time.perf_counter() - started
            done.join()
        assert waited > 0.8
        with engine.connect() as connection:
            assert connection.execute(text("SHOW lock_timeout")).scalar() == "300ms"
            assert connection.execute(text("SHOW statement_timeout")).scalar() == "5s"
    finally:
        engine.dispose()
