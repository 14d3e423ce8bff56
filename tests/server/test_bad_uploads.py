"""One test per kind of bad upload: each gets a clear error and leaves nothing stored."""

from __future__ import annotations

import zipfile
from collections.abc import Iterator
from pathlib import Path

import pytest
from sqlalchemy import func, select

from semantic3d.server.models import Job, Submission, UploadSession

from .conftest import (
    Harness,
    build_harness,
    ground_truth_arrays,
    labels_text,
    make_settings,
    noisy_predictions,
    submission_zip,
    zip_bytes,
)

MIB = 1 << 20


@pytest.fixture
def small_harness(tmp_path: Path, ground_truth_dir: Path) -> Iterator[Harness]:
    """A server with small caps: 64 KiB uploads, 16 KiB chunks, 1 MiB members once inflated."""
    settings = make_settings(
        tmp_path / "data", max_upload_bytes=64 << 10, max_chunk_bytes=16 << 10, max_member_bytes=MIB
    )
    yield from build_harness(settings, ground_truth_dir)


def good_members() -> dict[str, bytes]:
    predictions = noisy_predictions(ground_truth_arrays(), 0.9)
    return {f"{name}.labels": labels_text(values) for name, values in predictions.items()}


def assert_nothing_stored(harness: Harness, *, upload_kept: bool = False) -> None:
    with harness.state.factory() as session:
        assert session.scalar(select(func.count()).select_from(Submission)) == 0
        assert session.scalar(select(func.count()).select_from(Job)) == 0
        uploads = session.scalar(select(func.count()).select_from(UploadSession))
    if upload_kept:
        assert uploads == 1
        assert [p.parent for p in harness.stored_files()] == [harness.settings.uploads_dir]
    else:
        assert uploads == 0
        assert harness.stored_files() == []


def rejected(harness: Harness, data: bytes) -> dict:
    token = harness.user_token("mallory")
    response = harness.submit(token, data)
    assert response.status_code == 422, response.text
    body = response.json()
    assert body["error"].startswith("preds.zip: invalid submission")
    return body


def test_not_a_zip(harness: Harness) -> None:
    body = rejected(harness, b"1\n2\n3\n" * 100)
    assert any("not a zip archive" in p for p in body["problems"])
    assert_nothing_stored(harness)


def test_truncated_zip(harness: Harness) -> None:
    data = submission_zip(noisy_predictions(ground_truth_arrays(), 0.9))
    body = rejected(harness, data[: len(data) // 2])
    assert any("corrupt or truncated" in p for p in body["problems"])
    assert_nothing_stored(harness)


def test_zip_bomb_over_the_inflated_size_cap(small_harness: Harness) -> None:
    members = good_members()
    members["scan_a.labels"] = b"1\n" * (2 * MIB)  # 4 MiB inflated, a few KiB deflated
    data = zip_bytes(members)
    assert len(data) < 64 << 10
    body = rejected(small_harness, data)
    assert any("exceeds the limit" in p and "scan_a.labels" in p for p in body["problems"])
    assert_nothing_stored(small_harness)


def test_zip_bomb_by_compression_ratio(harness: Harness) -> None:
    members = good_members()
    members["scan_b.labels"] = b"1\n" * (4 * MIB)  # bzip2: far beyond any real label file
    data = zip_bytes(members, compression=zipfile.ZIP_BZIP2)
    body = rejected(harness, data)
    assert any("compression ratio" in p and "zip bomb" in p for p in body["problems"])
    assert_nothing_stored(harness)


def test_path_traversal(harness: Harness) -> None:
    members = good_members()
    members["../scan_a.labels"] = members.pop("scan_a.labels")
    body = rejected(harness, zip_bytes(members))
    assert any("path traversal" in p for p in body["problems"])
    assert_nothing_stored(harness)
    assert not (harness.settings.data_dir / "scan_a.labels").exists()


def test_absolute_path(harness: Harness) -> None:
    members = good_members()
    members["/etc/scan_a.labels"] = members.pop("scan_a.labels")
    body = rejected(harness, zip_bytes(members))
    assert any("absolute path" in p for p in body["problems"])
    assert_nothing_stored(harness)


def test_declared_size_over_the_cap(small_harness: Harness) -> None:
    token = small_harness.user_token("mallory")
    response = small_harness.client.post(
        "/api/uploads",
        json={"challenge": "toy", "size_bytes": (64 << 10) + 1},
        headers={"Authorization": f"Bearer {token}"},
    )
    assert response.status_code == 413
    assert "at most 65536 bytes" in response.json()["error"]
    assert_nothing_stored(small_harness)


def test_body_longer_than_declared(small_harness: Harness) -> None:
    token = small_harness.user_token("mallory")
    headers = {"Authorization": f"Bearer {token}"}
    created = small_harness.client.post(
        "/api/uploads", json={"challenge": "toy", "size_bytes": 1000}, headers=headers
    ).json()

    def body() -> Iterator[bytes]:  # no Content-Length: the cap is enforced while streaming
        for _ in range(4):
            yield b"x" * 700

    response = small_harness.client.put(
        f"/api/uploads/{created['id']}", params={"offset": 0}, content=body(), headers=headers
    )
    assert response.status_code == 413
    assert "passes the declared size 1000" in response.json()["error"]
    status = small_harness.client.get(f"/api/uploads/{created['id']}", headers=headers).json()
    assert status["received_bytes"] == 0  # the over-long chunk was cut back
    assert_nothing_stored(small_harness, upload_kept=True)


def test_chunk_over_the_chunk_cap(small_harness: Harness) -> None:
    token = small_harness.user_token("mallory")
    headers = {"Authorization": f"Bearer {token}"}
    created = small_harness.client.post(
        "/api/uploads", json={"challenge": "toy", "size_bytes": 40 << 10}, headers=headers
    ).json()
    response = small_harness.client.put(
        f"/api/uploads/{created['id']}",
        params={"offset": 0},
        content=b"x" * (20 << 10),
        headers=headers,
    )
    assert response.status_code == 413
    assert "at most 16384 bytes per PUT" in response.json()["error"]


def test_wrong_file_names(harness: Harness) -> None:
    members = good_members()
    members["scan_A.labels"] = members.pop("scan_a.labels")
    members["notes.txt"] = b"hello\n"
    body = rejected(harness, zip_bytes(members))
    problems = body["problems"]
    assert any("missing file 'scan_a.labels'" in p for p in problems)
    assert any("'scan_A.labels'" in p and "case-sensitive" in p for p in problems)
    assert any("unexpected file 'notes.txt'" in p for p in problems)
    assert_nothing_stored(harness)


def test_wrong_line_counts(harness: Harness) -> None:
    members = good_members()
    members["scan_a.labels"] = members["scan_a.labels"][:-2]  # one line short
    members["scan_b.labels"] += b"3\n"  # one line long
    body = rejected(harness, zip_bytes(members))
    assert any(
        "scan_a.labels: expected 3000 lines" in p and "found 2999" in p for p in body["problems"]
    )
    assert any(
        "scan_b.labels: expected 2000 lines" in p and "found 2001" in p for p in body["problems"]
    )
    assert_nothing_stored(harness)


@pytest.mark.parametrize("bad_value", [0, 9])
def test_label_values_outside_1_to_8(harness: Harness, bad_value: int) -> None:
    predictions = noisy_predictions(ground_truth_arrays(), 0.9)
    predictions["scan_a"] = predictions["scan_a"].copy()
    predictions["scan_a"][[10, 20]] = bad_value
    body = rejected(harness, submission_zip(predictions))
    text = " ".join(body["problems"])
    assert "scan_a.labels" in text and str(bad_value) in text and "line 11" in text
    assert_nothing_stored(harness)


def test_every_problem_is_reported_at_once(harness: Harness) -> None:
    members = good_members()
    members["scan_a.labels"] = b"1\n" * 10
    members["scan_b.labels"] = b"9\n" * 2000
    members["extra.labels"] = b"1\n"
    body = rejected(harness, zip_bytes(members))
    assert len(body["problems"]) >= 3


def test_malformed_utf8_in_a_label_file(harness: Harness) -> None:
    members = good_members()
    lines = members["scan_a.labels"].split(b"\n")
    lines[5] = b"\xff\xfe"
    members["scan_a.labels"] = b"\n".join(lines)
    body = rejected(harness, zip_bytes(members))
    assert any("scan_a.labels" in p and "line 6" in p for p in body["problems"])
    assert_nothing_stored(harness)


def test_malformed_utf8_in_the_request_body(harness: Harness) -> None:
    token = harness.user_token("mallory")
    response = harness.client.post(
        "/api/uploads",
        content=b'{"challenge": "toy\xff\xfe", "size_bytes": 10}',
        headers={"Authorization": f"Bearer {token}", "Content-Type": "application/json"},
    )
    assert response.status_code == 400
    assert response.json()["error"].startswith("malformed request body: expected UTF-8 JSON")
    assert_nothing_stored(harness)


def test_truncated_upload_is_not_queued(harness: Harness) -> None:
    token = harness.user_token("mallory")
    data = submission_zip(noisy_predictions(ground_truth_arrays(), 0.9))
    headers = {"Authorization": f"Bearer {token}"}
    created = harness.client.post(
        "/api/uploads", json={"challenge": "toy", "size_bytes": len(data)}, headers=headers
    ).json()
    harness.client.put(
        f"/api/uploads/{created['id']}", params={"offset": 0}, content=data[:-100], headers=headers
    )
    response = harness.finalize(token, created["id"])
    assert response.status_code == 409
    assert f"incomplete, {len(data) - 100} of {len(data)} bytes" in response.json()["error"]
    assert_nothing_stored(harness, upload_kept=True)


def test_unknown_challenge(harness: Harness) -> None:
    token = harness.user_token("mallory")
    response = harness.client.post(
        "/api/uploads",
        json={"challenge": "semantic-9", "size_bytes": 10},
        headers={"Authorization": f"Bearer {token}"},
    )
    assert response.status_code == 404
    assert "no challenge named 'semantic-9'" in response.json()["error"]


def test_empty_label_files(harness: Harness) -> None:
    body = rejected(harness, zip_bytes({"scan_a.labels": b"", "scan_b.labels": b""}))
    assert sum("expected" in p and "found 0" in p for p in body["problems"]) == 2
