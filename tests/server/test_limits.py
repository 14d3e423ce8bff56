"""Resource limits of the server, each a bounded test: CPU time, memory or wall time.

Hostile archives (a million-entry index, gigabytes of extra lines), sign-up floods,
stalled bodies, a locked database: each is answered within a budget, in-process over
the test client (loopback only).
"""

from __future__ import annotations

import asyncio
import functools
import io
import os
import sqlite3
import struct
import threading
import time
import zipfile
import zlib
from collections.abc import AsyncIterator, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
from sqlalchemy import event

from semantic3d.server.errors import RequestTimeoutError, ServiceUnavailableError
from semantic3d.server.services import accounts, upload_files
from semantic3d.server.services.accounts import hashing_slot, register_user
from semantic3d.server.services.upload_files import locked_part, write_chunk
from semantic3d.server.services.uploads import get_upload
from semantic3d.server.throttle import RateLimiter
from tests.budgets import Budget

from .conftest import (
    PASSWORD,
    Harness,
    build_harness,
    ground_truth_arrays,
    labels_text,
    make_settings,
    noisy_predictions,
    submission_zip,
    web_login,
    web_register,
)


def many_entries_zip(n_entries: int) -> bytes:
    """A zip of ``n_entries`` empty members with a ZIP64 end record, built directly."""
    local, central, offset = [], [], 0
    for i in range(n_entries):
        name = b"%07d" % i
        local += [struct.pack("<4s5H3L2H", b"PK\x03\x04", 20, 0, 0, 0, 0, 0, 0, 0, 7, 0), name]
        central += [
            struct.pack(
                "<4s6H3L5H2L", b"PK\x01\x02", 20, 20, 0, 0, 0, 0, 0, 0, 0, 7, 0, 0, 0, 0, 0, offset
            ),
            name,
        ]
        offset += 37
    directory = b"".join(central)
    at = offset + len(directory)
    zip64 = struct.pack(
        "<4sQ2H2L4Q", b"PK\x06\x06", 44, 45, 45, 0, 0, n_entries, n_entries, len(directory), offset
    ) + struct.pack("<4sLQL", b"PK\x06\x07", 0, at, 1)
    end = struct.pack("<4s4H2LH", b"PK\x05\x06", 0, 0, 0xFFFF, 0xFFFF, 0xFFFFFFFF, 0xFFFFFFFF, 0)
    return b"".join(local) + directory + zip64 + end


@pytest.fixture
def strict_harness(tmp_path: Path, ground_truth_dir: Path) -> Iterator[Harness]:
    """Small rate limits: 2 rejected uploads an hour, 3 sign-ups per address."""
    settings = make_settings(
        tmp_path / "data",
        max_rejected_uploads=2,
        register_max_per_ip=3,
        password_hash_wait_s=0.3,
    )
    yield from build_harness(settings, ground_truth_dir)


# 1: the archive index ---------------------------------------------------------------------


def test_a_million_entry_style_index_is_refused_before_it_is_built(
    strict_harness: Harness,
) -> None:
    # 100,000 empty entries (7 MB): zipfile's index of them costs ~1.5 s CPU and ~50 MB
    # (a million: 15 s and +470 MB); refused from the end record it takes milliseconds.
    harness = strict_harness
    token = harness.user_token("mallory")
    archive = many_entries_zip(100_000)
    upload_id = harness.upload(token, archive, chunk=8 << 20)
    with Budget() as budget:
        response = harness.finalize(token, upload_id)
    assert response.status_code == 422, response.text
    assert response.json()["problems"] == [
        "archive holds 100000 members, more than the limit of 10000"
    ]
    # What building the index costs in this process, measured the same way (process CPU
    # counts every thread, so background threads of earlier tests inflate both alike).
    with Budget(traced=False) as index:
        assert len(zipfile.ZipFile(io.BytesIO(archive)).infolist()) == 100_000
    assert budget.peak_mb < 10, f"finalize {budget}"
    assert budget.cpu_s < 0.5 * index.cpu_s, f"finalize {budget}; index {index}"
    assert harness.stored_files() == []


def test_a_record_signature_in_the_end_records_offset_field_hides_nothing(
    strict_harness: Harness,
) -> None:
    # The 4-byte trick: the classic end record's offset field set to "PK\x05\x06". A
    # search for the last record signature found a fake record there and skipped every
    # check, while zipfile indexed all 100,000 entries (~1.5 s, ~50 MB; 1 M: +6 s, +500 MB).
    harness = strict_harness
    token = harness.user_token("mallory")
    archive = bytearray(many_entries_zip(100_000))
    archive[-6:-2] = b"PK\x05\x06"
    upload_id = harness.upload(token, bytes(archive), chunk=8 << 20)
    with Budget() as budget:
        response = harness.finalize(token, upload_id)
    assert response.status_code == 422, response.text
    assert response.json()["problems"] == [
        "archive holds 100000 members, more than the limit of 10000"
    ]
    with Budget(traced=False) as index:
        assert len(zipfile.ZipFile(io.BytesIO(bytes(archive))).infolist()) == 100_000
    assert budget.peak_mb < 10, f"finalize {budget}"
    assert budget.cpu_s < 0.5 * index.cpu_s, f"finalize {budget}; index {index}"
    assert harness.stored_files() == []


def test_rejected_uploads_count_toward_a_rate_limit(strict_harness: Harness) -> None:
    harness = strict_harness
    token = harness.user_token("mallory")
    assert harness.submit(token, b"not a zip" * 100).status_code == 422
    corrupted = harness.upload(token, b"not a zip" * 100, sha256="0" * 64)
    response = harness.finalize(token, corrupted)
    assert response.status_code == 400 and "corrupted in transit" in response.json()["error"]
    headers = {"Authorization": f"Bearer {token}"}
    body = {"challenge": "toy", "size_bytes": 100, "filename": "again.zip"}
    refused = harness.client.post("/api/uploads", json=body, headers=headers)
    assert refused.status_code == 429
    assert refused.json()["error"].startswith("too many invalid submissions from your account: 2")
    assert 3500 < int(refused.headers["Retry-After"]) <= 3600
    # Another account is not affected.
    other = harness.user_token("honest")
    good = submission_zip(noisy_predictions(ground_truth_arrays(), 0.9))
    assert harness.submit(other, good).status_code == 201


# 3: validation stops reading at expected + 1 lines -------------------------------------------


def test_extra_lines_are_not_read_to_the_end(harness: Harness) -> None:
    # scan_a expects 3000 lines; this member has 32 M (64 MiB inflated, 1028:1 like the
    # attack's 2 GiB ones). Reading it all took ~0.3 s CPU here (2 GiB: 24 s); its
    # declared size is more than 3001 lines can take, so it is not read at all.
    members = {f"{n}.labels": labels_text(v) for n, v in ground_truth_arrays().items()}
    other = harness.user_token("honest")
    honest = harness.upload(other, submission_zip(noisy_predictions(ground_truth_arrays(), 0.9)))
    with Budget(traced=False) as honest_budget:
        assert harness.finalize(other, honest).status_code == 201
    token = harness.user_token("mallory")
    members["scan_a.labels"] = b"1\n" * (32 << 20)
    with_extra = zipfile_bytes(members)
    upload_id = harness.upload(token, with_extra)
    with Budget(traced=False) as budget:
        response = harness.finalize(token, upload_id)
    assert response.status_code == 422
    assert (
        "scan_a.labels: 67108864 bytes once inflated, more than 3000 lines can take (at most "
        "48016 bytes, 16 a line); not read" in response.json()["problems"]
    )
    # Its extra lines cost less than half of what reading the member to its end costs in
    # this process (each measured the same way; the honest finalize checks the same scans).
    with Budget(traced=False) as reading, zipfile.ZipFile(io.BytesIO(with_extra)) as archive:
        assert archive.read("scan_a.labels").count(b"\n") == 32 << 20
    extra_cpu_s = budget.cpu_s - honest_budget.cpu_s
    assert extra_cpu_s < 0.5 * reading.cpu_s, f"{budget}; honest {honest_budget}; read {reading}"


def test_gigabytes_without_a_line_end_are_refused_before_inflating(harness: Harness) -> None:
    # A 4 MB upload whose two members inflate to 2 GiB of "1" each, with no line end
    # (deflate at ~1030:1, under the ratio and size caps): counting lines never stopped
    # early, so both were inflated to the end to be refused, ~10 s of CPU. A scan of
    # 3000 points takes at most 3001 x 16 bytes: the declared 2 GiB are refused unread.
    members = {name: ones_without_a_line_end(2 << 30) for name in ("scan_a", "scan_b")}
    archive = raw_deflated_zip({f"{name}.labels": member for name, member in members.items()})
    assert len(archive) < 5 << 20
    token = harness.user_token("mallory")
    upload_id = harness.upload(token, archive, chunk=8 << 20)
    with Budget() as budget:
        response = harness.finalize(token, upload_id)
    assert response.status_code == 422
    assert response.json()["problems"] == [
        f"{name}.labels: 2147483648 bytes once inflated, more than {n} lines can take (at "
        f"most {(n + 1) * 16} bytes, 16 a line); not read"
        for name, n in (("scan_a", 3000), ("scan_b", 2000))
    ]
    # What inflating an eighth of one member (256 of its 2,048 MiB) costs in this process.
    with Budget(traced=False) as inflating:
        assert inflated_bytes(members["scan_a"][0], 256 << 20) == 256 << 20
    assert budget.peak_mb < 10, str(budget)
    assert budget.cpu_s < 0.5 * inflating.cpu_s, f"finalize {budget}; inflating {inflating}"


@functools.cache
def ones_without_a_line_end(n_bytes: int) -> tuple[bytes, int, int]:
    """A raw deflate stream of ``n_bytes`` bytes of ``1``, its CRC-32 and ``n_bytes``.

    Built from one fully flushed MiB repeated (a full flush resets the compressor, so
    every MiB compresses to the same bytes): milliseconds instead of deflating gigabytes.
    """
    block = b"1" * (1 << 20)
    compressor = zlib.compressobj(9, zlib.DEFLATED, -15)
    piece = compressor.compress(block) + compressor.flush(zlib.Z_FULL_FLUSH)
    stream = piece * (n_bytes >> 20) + compressor.flush(zlib.Z_FINISH)
    crc = 0
    for _ in range(n_bytes >> 20):
        crc = zlib.crc32(block, crc)
    return stream, crc, n_bytes


def inflated_bytes(stream: bytes, limit: int) -> int:
    """How many bytes the raw deflate ``stream`` inflates to, stopping at ``limit``."""
    inflater = zlib.decompressobj(-15)
    total = 0
    while total < limit and not inflater.eof:
        piece = inflater.decompress(stream, 1 << 20)
        stream = inflater.unconsumed_tail
        total += len(piece)
        if not piece:
            break
    return total


def raw_deflated_zip(members: dict[str, tuple[bytes, int, int]]) -> bytes:
    """A zip of already deflated members (``name -> (stream, crc, size)``)."""
    local, central, offset = [], [], 0
    for name, (stream, crc, size) in members.items():
        encoded = name.encode()
        header = struct.pack(
            "<4s5H3L2H", b"PK\x03\x04", 20, 0, 8, 0, 0x21, crc, len(stream), size, len(encoded), 0
        )
        local += [header, encoded, stream]
        central += [
            struct.pack(
                "<4s6H3L5H2L",
                b"PK\x01\x02",
                20,
                20,
                0,
                8,
                0,
                0x21,
                crc,
                len(stream),
                size,
                len(encoded),
                0,
                0,
                0,
                0,
                0,
                offset,
            ),
            encoded,
        ]
        offset += len(header) + len(encoded) + len(stream)
    directory = b"".join(central)
    end = struct.pack(
        "<4s4H2LH", b"PK\x05\x06", 0, 0, len(members), len(members), len(directory), offset, 0
    )
    return b"".join(local) + directory + end


def zipfile_bytes(members: dict[str, bytes]) -> bytes:
    """A deflated zip, at the fastest level (64 MiB of one line compress in ~0.2 s)."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as archive:
        for name, data in members.items():
            archive.writestr(name, data)
    return buffer.getvalue()


# 4: registration and password hashing -----------------------------------------------------


def test_registration_is_throttled_per_address_before_hashing(
    strict_harness: Harness, monkeypatch: pytest.MonkeyPatch
) -> None:
    client = strict_harness.client
    hashed: list[str] = []
    real_hash = accounts.hash_password

    def counting_hash(password: str) -> str:
        hashed.append(password)
        return real_hash(password)

    monkeypatch.setattr(accounts, "hash_password", counting_hash)
    accepted: list[Budget] = []
    for i in range(3):
        with Budget(traced=False) as budget:
            assert web_register(client, f"user{i}").status_code == 303
        accepted.append(budget)
        client.post("/logout", data={"csrf_token": ""})
        client.cookies.clear()
    assert len(hashed) == 3
    with Budget(traced=False) as refused_budget:
        refused = web_register(client, "user3")
    assert refused.status_code == 429
    assert "too many registrations from your address: 3" in refused.text
    assert int(refused.headers["Retry-After"]) > 3500
    assert len(hashed) == 3, "a throttled registration was hashed"
    # Not a fixed number of seconds: what an accepted sign-up (one argon2 hash of 64 MiB)
    # costs on this machine in this run, measured the same way.
    cheapest = min(budget.cpu_s for budget in accepted)
    assert refused_budget.cpu_s < 0.5 * cheapest, f"refused {refused_budget}; accepted {cheapest}"


def _rss_mb() -> float:
    with Path("/proc/self/statm").open() as handle:
        return int(handle.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e6


@pytest.mark.skipif(not Path("/proc/self/statm").exists(), reason="needs /proc")
def test_concurrent_registrations_hash_two_at_a_time(
    harness: Harness, monkeypatch: pytest.MonkeyPatch
) -> None:
    # argon2id takes 64 MiB per hash: 8 sign-ups at once take +0.5 GB unbounded (40: +2.4 GB).
    settings = harness.settings
    assert settings.password_hash_concurrency == 2
    running = peak_running = 0
    lock = threading.Lock()
    real_hash = accounts.hash_password

    def counting_hash(password: str) -> str:
        nonlocal running, peak_running
        with lock:
            running += 1
            peak_running = max(peak_running, running)
        try:
            return real_hash(password)
        finally:
            with lock:
                running -= 1

    monkeypatch.setattr(accounts, "hash_password", counting_hash)
    baseline = _rss_mb()
    peak = baseline
    stop = threading.Event()

    def sample() -> None:
        nonlocal peak
        while not stop.is_set():
            peak = max(peak, _rss_mb())
            time.sleep(0.002)

    sampler = threading.Thread(target=sample)
    sampler.start()
    limiter = RateLimiter(100, 3600)
    try:
        with ThreadPoolExecutor(8) as pool:
            users = list(
                pool.map(
                    lambda i: register_user(
                        harness.state.factory,
                        settings,
                        limiter,
                        f"crowd{i}",
                        PASSWORD,
                        address=f"10.0.0.{i}",
                    ),
                    range(8),
                )
            )
    finally:
        stop.set()
        sampler.join()
    assert len(users) == 8
    assert peak_running == 2
    assert peak - baseline < 2 * 67 + 100, f"+{peak - baseline:.0f} MB RSS"


def test_login_waits_for_a_hashing_slot_then_answers_503(strict_harness: Harness) -> None:
    harness = strict_harness
    harness.user_token("grace")
    settings = harness.settings
    held = [hashing_slot(settings) for _ in range(settings.password_hash_concurrency)]
    for slot in held:
        slot.__enter__()
    try:
        started = time.perf_counter()
        response = web_login(harness.client, "grace", PASSWORD)
        # the slots are held throughout: an unbounded wait would never answer. The wait is
        # 0.3 s; the bound leaves room for a loaded machine (2 s failed under load 10)
        assert time.perf_counter() - started < 10
    finally:
        for slot in held:
            slot.__exit__(None, None, None)
    assert response.status_code == 503
    assert response.headers["Retry-After"] == "1"
    assert "busy checking passwords" in response.text
    # The refused attempt did not count as a failure: the next one logs in.
    assert web_login(harness.client, "grace", PASSWORD).status_code == 303


def test_hashing_slot_times_out(harness: Harness) -> None:
    settings = make_settings(
        harness.settings.data_dir, password_hash_concurrency=1, password_hash_wait_s=0.1
    )
    with hashing_slot(settings):
        started = time.perf_counter()
        with (
            pytest.raises(ServiceUnavailableError, match="busy checking passwords"),
            hashing_slot(settings),
        ):
            pass
        assert time.perf_counter() - started < 1


# 6: stalled bodies, races, the database ----------------------------------------------------


def test_a_stalled_put_is_cut_off_and_releases_the_lock(harness: Harness) -> None:
    settings = make_settings(harness.settings.data_dir, upload_read_timeout_s=0.2)
    token = harness.user_token("slow")
    created = harness.client.post(
        "/api/uploads",
        json={"challenge": "toy", "size_bytes": 100},
        headers={"Authorization": f"Bearer {token}"},
    ).json()
    user_id = harness.client.get("/api/me", headers={"Authorization": f"Bearer {token}"})
    assert user_id.status_code == 200

    async def stalls() -> AsyncIterator[bytes]:
        yield b"x" * 10
        await asyncio.sleep(3600)
        yield b"never"

    with harness.state.factory() as session:
        from semantic3d.server.models import UploadSession

        owner = session.get_one(UploadSession, created["id"]).user_id
    upload = get_upload(harness.state.factory, settings, created["id"], user_id=owner)
    started = time.perf_counter()
    with pytest.raises(RequestTimeoutError, match=r"no data for 0\.2 s; the bytes received"):
        asyncio.run(write_chunk(settings, upload, offset=0, content_length=None, chunks=stalls()))
    assert time.perf_counter() - started < 2
    assert upload_files.received_bytes(settings, upload.id) == 10  # kept: resume from there
    with locked_part(settings, upload.id):  # the lock is free again
        pass


def test_deleting_an_upload_during_its_finalize_is_a_clean_409(
    harness: Harness, monkeypatch: pytest.MonkeyPatch
) -> None:
    from semantic3d.server.services import submissions

    token = harness.user_token("racer")
    headers = {"Authorization": f"Bearer {token}"}
    upload_id = harness.upload(token, submission_zip(noisy_predictions(ground_truth_arrays(), 0.9)))
    validating, release = threading.Event(), threading.Event()
    real_validate = submissions.validate_submission

    def slow_validate(*args: object, **kwargs: object) -> None:
        validating.set()
        assert release.wait(10)
        real_validate(*args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(submissions, "validate_submission", slow_validate)
    with ThreadPoolExecutor(1) as pool:
        finalizing = pool.submit(harness.finalize, token, upload_id)
        assert validating.wait(10)
        deleted = harness.client.delete(f"/api/uploads/{upload_id}", headers=headers)
        release.set()
        finalized = finalizing.result()
    assert deleted.status_code == 409
    assert (
        "cannot be deleted now: another request is writing or finalizing it"
        in (deleted.json()["error"])
    )
    assert finalized.status_code == 201, finalized.text


def test_a_locked_database_answers_503_soon_and_reads_still_work(
    tmp_path: Path, ground_truth_dir: Path
) -> None:
    settings = make_settings(tmp_path / "data", sqlite_busy_timeout_s=0.3)
    for harness in build_harness(settings, ground_truth_dir):
        token = harness.user_token("grace")
        headers = {"Authorization": f"Bearer {token}"}
        assert harness.client.get("/api/me", headers=headers).status_code == 200
        blocker = sqlite3.connect(settings.data_dir / "semantic3d.sqlite3", isolation_level=None)
        blocker.execute("BEGIN IMMEDIATE")
        try:
            started = time.perf_counter()
            body = {"challenge": "toy", "size_bytes": 100}
            response = harness.client.post("/api/uploads", json=body, headers=headers)
            elapsed = time.perf_counter() - started
            me = harness.client.get("/api/me", headers=headers)
        finally:
            blocker.execute("ROLLBACK")
            blocker.close()
        assert response.status_code == 503, response.text
        assert response.headers["Retry-After"] == "5"
        assert response.json()["error"] == "the database is busy; try again in a few seconds"
        assert elapsed < 3
        assert me.status_code == 200  # token auth reads; it does not need the write lock
        assert harness.client.post("/api/uploads", json=body, headers=headers).status_code == 201


def test_token_use_is_recorded_at_most_once_a_minute(harness: Harness) -> None:
    token = harness.user_token("busy")
    headers = {"Authorization": f"Bearer {token}"}
    writes: list[str] = []

    def count(conn: object, cursor: object, statement: str, *args: object) -> None:
        if statement.lstrip().upper().startswith("UPDATE API_TOKENS"):
            writes.append(statement)

    event.listen(harness.state.engine, "before_cursor_execute", count)
    try:
        for _ in range(20):
            assert harness.client.get("/api/me", headers=headers).status_code == 200
    finally:
        event.remove(harness.state.engine, "before_cursor_execute", count)
    assert len(writes) == 1


@pytest.mark.parametrize("runtime", ["1e308", "10000001", "Infinity", "NaN", "-1"])
def test_run_time_is_bounded_and_finite(harness: Harness, runtime: str) -> None:
    token = harness.user_token("boaster")
    upload_id = harness.upload(token, submission_zip(noisy_predictions(ground_truth_arrays(), 0.9)))
    response = harness.client.post(
        f"/api/uploads/{upload_id}/finalize",
        content=b'{"method": {"name": "m", "runtime_s": %s}}' % runtime.encode(),
        headers={"Authorization": f"Bearer {token}", "Content-Type": "application/json"},
    )
    assert response.status_code == 422, response.text
    assert any(p.startswith("body.method.runtime_s") for p in response.json()["problems"])
    assert harness.finalize(token, upload_id, runtime_s=1e7).status_code == 201


def test_data_files_are_private(harness: Harness) -> None:
    settings = harness.settings
    harness.submit(harness.user_token("grace"), submission_zip(ground_truth_arrays()))
    for folder in (
        settings.data_dir,
        settings.uploads_dir,
        settings.submissions_dir,
        settings.ground_truth_dir,
    ):
        assert folder.stat().st_mode & 0o777 == 0o700, folder
    database = settings.data_dir / "semantic3d.sqlite3"
    for path in (database, database.with_name(database.name + "-wal")):
        assert path.stat().st_mode & 0o777 == 0o600, path


def test_existing_data_dir_is_made_private(tmp_path: Path) -> None:
    data_dir = tmp_path / "data"
    (data_dir / "uploads").mkdir(parents=True, mode=0o755)
    data_dir.chmod(0o755)
    (data_dir / "semantic3d.sqlite3").touch(mode=0o644)
    settings = make_settings(data_dir)
    from semantic3d.server.db import create_db_engine

    create_db_engine(settings).dispose()
    assert data_dir.stat().st_mode & 0o777 == 0o700
    assert (data_dir / "uploads").stat().st_mode & 0o777 == 0o700
    assert (data_dir / "semantic3d.sqlite3").stat().st_mode & 0o777 == 0o600


def test_rate_limiter_window() -> None:
    now = [0.0]
    limiter = RateLimiter(2, 10, clock=lambda: now[0])
    limiter.check_and_hit("a", "tries")
    limiter.check_and_hit("a", "tries")
    with pytest.raises(Exception, match=r"too many tries: 2 in the last 10 s \(at most 2\)"):
        limiter.check_and_hit("a", "tries")
    limiter.check_and_hit("b", "tries")
    now[0] = 10.5
    limiter.check_and_hit("a", "tries")
    assert limiter.count("a") == 1
