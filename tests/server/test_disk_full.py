"""A full disk never wedges the server: 507 before bytes are taken, recovery by itself.

Simulated (``shutil.disk_usage`` and ``ENOSPC`` on the write path) everywhere, and for
real on a small tmpfs when the tests run as root (skipped otherwise).
"""

from __future__ import annotations

import errno
import os
import shutil
import subprocess
from collections.abc import Iterator
from datetime import timedelta
from pathlib import Path
from typing import Any

import pytest
from sqlalchemy import update

from semantic3d.server.errors import InsufficientStorageError
from semantic3d.server.models import UploadSession, utc_now
from semantic3d.server.services import upload_files, uploads
from semantic3d.server.services.uploads import expire_uploads
from semantic3d.server.worker import Worker

from .conftest import (
    PASSWORD,
    Harness,
    build_harness,
    ground_truth_arrays,
    make_settings,
    noisy_predictions,
    submission_zip,
    web_login,
)

MIB = 1 << 20


def good_zip() -> bytes:
    return submission_zip(noisy_predictions(ground_truth_arrays(), 0.9))


def fake_free_space(monkeypatch: pytest.MonkeyPatch, free_bytes: list[int]) -> None:
    real = shutil.disk_usage

    def disk_usage(path: Any) -> Any:
        usage = real(path)
        return usage._replace(free=free_bytes[0])

    monkeypatch.setattr(upload_files.shutil, "disk_usage", disk_usage)


@pytest.fixture
def margin_harness(tmp_path: Path, ground_truth_dir: Path) -> Iterator[Harness]:
    settings = make_settings(tmp_path / "data", min_free_bytes=10 * MIB)
    yield from build_harness(settings, ground_truth_dir)


def test_uploads_are_refused_with_507_before_the_margin_is_touched(
    margin_harness: Harness, monkeypatch: pytest.MonkeyPatch
) -> None:
    harness = margin_harness
    token = harness.user_token("grace")
    headers = {"Authorization": f"Bearer {token}"}
    data = good_zip()
    free = [10 * MIB + len(data) // 2]
    fake_free_space(monkeypatch, free)
    body = {"challenge": "toy", "size_bytes": len(data), "filename": "preds.zip"}
    opened = harness.client.post("/api/uploads", json=body, headers=headers)
    assert opened.status_code == 507
    assert opened.json()["error"].startswith(
        f"not enough free disk space on the server for {len(data)} more bytes"
    )
    free[0] = 10 * MIB + len(data)
    upload_id = harness.client.post("/api/uploads", json=body, headers=headers).json()["id"]
    free[0] = 10 * MIB + 100  # something else filled the disk meanwhile
    put = harness.client.put(
        f"/api/uploads/{upload_id}", params={"offset": 0}, content=data, headers=headers
    )
    assert put.status_code == 507
    assert upload_files.received_bytes(harness.settings, upload_id) == 0
    # Everything else still works (the margin is there for the database) ...
    assert web_login(harness.client, "grace", PASSWORD).status_code == 303
    assert harness.client.get(f"/api/uploads/{upload_id}", headers=headers).status_code == 200
    # ... and once space is free again, the same upload goes on.
    free[0] = 1 << 40
    put = harness.client.put(
        f"/api/uploads/{upload_id}", params={"offset": 0}, content=data, headers=headers
    )
    assert put.status_code == 200
    assert harness.finalize(token, upload_id).status_code == 201


def test_enospc_while_writing_keeps_nothing_of_the_chunk(
    harness: Harness, monkeypatch: pytest.MonkeyPatch
) -> None:
    token = harness.user_token("grace")
    headers = {"Authorization": f"Bearer {token}"}
    data = good_zip()
    body = {"challenge": "toy", "size_bytes": len(data), "filename": "preds.zip"}
    upload_id = harness.client.post("/api/uploads", json=body, headers=headers).json()["id"]
    half = len(data) // 2
    assert (
        harness.client.put(
            f"/api/uploads/{upload_id}", params={"offset": 0}, content=data[:half], headers=headers
        ).status_code
        == 200
    )
    real_append = upload_files._append

    def full_disk(handle: Any, upload_id: str, position: int, block: bytearray) -> None:
        handle.write(block[:100])  # a partial write, then the disk is full
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(upload_files, "_append", full_disk)
    put = harness.client.put(
        f"/api/uploads/{upload_id}", params={"offset": half}, content=data[half:], headers=headers
    )
    assert put.status_code == 507
    assert "disk filled up while receiving the chunk at offset" in put.json()["error"]
    assert upload_files.received_bytes(harness.settings, upload_id) == half
    monkeypatch.setattr(upload_files, "_append", real_append)
    put = harness.client.put(
        f"/api/uploads/{upload_id}", params={"offset": half}, content=data[half:], headers=headers
    )
    assert put.status_code == 200
    assert harness.finalize(token, upload_id).status_code == 201


def test_deleting_frees_the_file_even_when_the_database_cannot_write(
    harness: Harness, monkeypatch: pytest.MonkeyPatch
) -> None:
    token = harness.user_token("grace")
    upload_id = harness.upload(token, good_zip())
    part = upload_files.part_path(harness.settings, upload_id)
    with harness.state.factory() as session:
        session.execute(update(UploadSession).values(expires_at=utc_now() - timedelta(seconds=1)))
        session.commit()

    def full(*args: object, **kwargs: object) -> Any:
        raise InsufficientStorageError("the server's disk is full")

    monkeypatch.setattr(uploads, "write_transaction", full)
    with pytest.raises(InsufficientStorageError):
        expire_uploads(harness.state.factory, harness.settings)
    assert not part.exists()  # the space is free although the row could not go
    # The worker's sweep carries on past the failure (and the queue sweep still runs).
    assert Worker(harness.settings, harness.state.factory).run_once() is False
    monkeypatch.undo()
    assert expire_uploads(harness.state.factory, harness.settings) == 1
    with harness.state.factory() as session:
        assert session.get(UploadSession, upload_id) is None


@pytest.fixture
def tiny_disk(tmp_path: Path) -> Iterator[Path]:
    """A 6 MiB tmpfs (root only; skipped when it cannot be mounted)."""
    mount_point = tmp_path / "tiny"
    mount_point.mkdir()
    if os.geteuid() != 0 or shutil.which("mount") is None:
        pytest.skip("mounting a tmpfs needs root")
    mounted = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=6m,mode=0700", "tmpfs", str(mount_point)],
        capture_output=True,
        check=False,
    )
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs: {mounted.stderr.decode().strip()}")
    try:
        yield mount_point
    finally:
        subprocess.run(["umount", "-l", str(mount_point)], check=False)


def fill(path: Path) -> None:
    """Write zeros to ``path`` until the file system is full."""
    with path.open("ab", buffering=0) as handle:
        block = b"\0" * (64 << 10)
        try:
            while True:
                handle.write(block)
        except OSError as exc:
            assert exc.errno == errno.ENOSPC
        block = b"\0" * 512
        try:
            while True:
                handle.write(block)
        except OSError:
            pass


def test_a_really_full_disk_answers_507_and_recovers_by_itself(
    tiny_disk: Path, ground_truth_dir: Path
) -> None:
    settings = make_settings(tiny_disk / "data", min_free_bytes=1 * MIB)
    for harness in build_harness(settings, ground_truth_dir):
        token = harness.user_token("grace")
        headers = {"Authorization": f"Bearer {token}"}
        body = {"challenge": "toy", "size_bytes": 6 * MIB, "filename": "big.zip"}
        big = harness.client.post("/api/uploads", json=body, headers=headers)
        assert big.status_code == 507  # refused at once: it could never fit
        body["size_bytes"] = 3 * MIB
        upload_id = harness.client.post("/api/uploads", json=body, headers=headers).json()["id"]
        put = harness.client.put(
            f"/api/uploads/{upload_id}",
            params={"offset": 0},
            content=b"\0" * (2 * MIB),
            headers=headers,
        )
        assert put.status_code == 200

        # Something else fills the disk to the last byte.
        filler = tiny_disk / "filler"
        fill(filler)
        put = harness.client.put(
            f"/api/uploads/{upload_id}",
            params={"offset": 2 * MIB},
            content=b"\0" * MIB,
            headers=headers,
        )
        assert put.status_code == 507
        login = web_login(harness.client, "grace", PASSWORD)  # writes an attempt record
        assert login.status_code == 507, login.text
        assert "the server&#39;s disk is full" in login.text
        assert harness.client.get("/api/me", headers=headers).status_code == 200
        # Deleting works on a full disk: the file goes first, which makes room for the row.
        deleted = harness.client.delete(f"/api/uploads/{upload_id}", headers=headers)
        assert deleted.status_code == 204, deleted.text
        assert not upload_files.part_path(settings, upload_id).exists()
        assert web_login(harness.client, "grace", PASSWORD).status_code == 303

        # The disk fills up again, and is freed: everything works without a restart.
        fill(filler)
        assert web_login(harness.client, "grace", PASSWORD).status_code == 507
        filler.unlink()
        assert web_login(harness.client, "grace", PASSWORD).status_code == 303
        assert harness.submit(token, good_zip()).status_code == 201
