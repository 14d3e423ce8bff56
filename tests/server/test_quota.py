"""Submission limits: cooldown per challenge, one in flight, failures count, race-free checks."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
from sqlalchemy import func, select

from semantic3d.evaluation import MethodInfo
from semantic3d.server.errors import ThrottledError
from semantic3d.server.models import Submission
from semantic3d.server.services.submissions import finalize_upload

from .conftest import (
    Harness,
    build_harness,
    ground_truth_arrays,
    make_settings,
    noisy_predictions,
    submission_zip,
)


@pytest.fixture
def cooldown_harness(tmp_path: Path, ground_truth_dir: Path) -> Iterator[Harness]:
    """A server with the default 72 h cooldown; uploads live 96 h, so finalize refuses."""
    yield from build_harness(
        make_settings(tmp_path / "data", submission_cooldown_h=72, upload_session_ttl_s=96 * 3600),
        ground_truth_dir,
    )


def _data(seed: int = 1) -> bytes:
    return submission_zip(noisy_predictions(ground_truth_arrays(), 0.9, seed=seed))


def test_second_submission_within_the_cooldown_is_refused(cooldown_harness: Harness) -> None:
    harness = cooldown_harness
    token = harness.user_token("alice")
    assert harness.submit(token, _data()).status_code == 201
    harness.work()
    second = harness.submit(token, _data(2))
    assert second.status_code == 429
    assert "every 72 h" in second.json()["error"]
    retry = int(second.headers["Retry-After"])
    assert 71 * 3600 < retry <= 72 * 3600 + 1
    # Another account is not affected.
    assert harness.submit(harness.user_token("bob"), _data()).status_code == 201


def test_cooldown_is_checked_before_a_large_upload_starts(
    tmp_path: Path, ground_truth_dir: Path
) -> None:
    harnesses = build_harness(
        make_settings(tmp_path / "data", submission_cooldown_h=72), ground_truth_dir
    )
    harness = next(harnesses)
    token = harness.user_token("alice")
    headers = {"Authorization": f"Bearer {token}"}
    harness.submit(token, _data())
    harness.work()
    # The 72 h cooldown outlasts a 48 h upload session: refused before any byte is sent.
    refused = harness.client.post(
        "/api/uploads", json={"challenge": "toy", "size_bytes": 6 << 30}, headers=headers
    )
    assert refused.status_code == 429
    assert "would expire before then" in refused.json()["error"]
    retry = int(refused.headers["Retry-After"])
    assert 23 * 3600 < retry <= 24 * 3600 + 1
    assert not list(harness.settings.uploads_dir.iterdir())
    harnesses.close()


def test_an_upload_finishing_after_the_cooldown_may_start_during_it(
    cooldown_harness: Harness,
) -> None:
    harness = cooldown_harness
    token = harness.user_token("alice")
    harness.submit(token, _data())
    harness.work()
    # Finalize still enforces the cooldown, and keeps the upload for later.
    upload_id = harness.upload(token, _data(2))
    assert harness.finalize(token, upload_id).status_code == 429
    status = harness.client.get(
        f"/api/uploads/{upload_id}", headers={"Authorization": f"Bearer {token}"}
    )
    assert status.status_code == 200 and status.json()["complete"] is True


def test_failed_submissions_count_toward_the_quota(cooldown_harness: Harness) -> None:
    harness = cooldown_harness
    token = harness.user_token("alice")
    submission_id = harness.submit(token, _data()).json()["id"]
    with harness.state.factory() as session:
        stored = (
            harness.settings.submissions_dir / session.get(Submission, submission_id).stored_name
        )
    stored.write_bytes(b"garbage")  # the evaluation will fail
    harness.work()
    status = harness.client.get(
        f"/api/submissions/{submission_id}", headers={"Authorization": f"Bearer {token}"}
    ).json()
    assert status["status"] == "failed"
    assert harness.submit(token, _data(2)).status_code == 429


def test_one_submission_in_flight_per_account(harness: Harness) -> None:
    token = harness.user_token("alice")
    assert harness.submit(token, _data()).status_code == 201
    second = harness.submit(token, _data(2))
    assert second.status_code == 429
    assert "still being evaluated" in second.json()["error"]
    harness.work()
    assert harness.submit(token, _data(2)).status_code == 201


def _race(harness: Harness, upload_ids: list[str], *, user_id: int) -> list[str]:
    """Finalize every upload at the same instant from its own thread; the outcomes."""
    barrier = threading.Barrier(len(upload_ids))
    outcomes: list[str] = []
    lock = threading.Lock()

    def attempt(upload_id: str) -> None:
        barrier.wait()
        try:
            finalize_upload(
                harness.state.factory,
                harness.settings,
                harness.state.challenges,
                user_id=user_id,
                upload_id=upload_id,
                method=MethodInfo("racer"),
            )
            result = "ok"
        except ThrottledError:
            result = "throttled"
        with lock:
            outcomes.append(result)

    threads = [threading.Thread(target=attempt, args=(u,)) for u in upload_ids]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    return outcomes


@pytest.mark.parametrize("cooldown_h", [0, 72])
def test_simultaneous_finalizes_cannot_both_pass(
    tmp_path: Path, ground_truth_dir: Path, cooldown_h: float
) -> None:
    harness_iter = build_harness(
        make_settings(
            tmp_path / "data",
            submission_cooldown_h=cooldown_h,
            max_open_uploads=8,
            upload_session_ttl_s=96 * 3600,  # uploads may start during the cooldown
        ),
        ground_truth_dir,
    )
    harness = next(harness_iter)
    try:
        token = harness.user_token("alice")
        user_id = 1
        rounds, threads_per_round = 3, 4
        for round_index in range(rounds):
            upload_ids = [harness.upload(token, _data(seed)) for seed in range(threads_per_round)]
            outcomes = _race(harness, upload_ids, user_id=user_id)
            expected_ok = 1 if round_index == 0 or cooldown_h == 0 else 0
            assert sorted(outcomes).count("ok") == expected_ok, outcomes
            harness.work()
            for upload_id in upload_ids:  # leftovers of refused attempts
                harness.client.delete(
                    f"/api/uploads/{upload_id}", headers={"Authorization": f"Bearer {token}"}
                )
        with harness.state.factory() as session:
            total = session.scalar(select(func.count()).select_from(Submission))
        assert total == (rounds if cooldown_h == 0 else 1)
    finally:
        harness_iter.close()


def test_an_upload_to_a_challenge_closed_meanwhile_is_not_queued(harness: Harness) -> None:
    from semantic3d.server.services.challenges import set_challenge_open

    token = harness.user_token("alice")
    upload_id = harness.upload(token, _data())
    set_challenge_open(harness.state.factory, "toy", is_open=False)
    refused = harness.finalize(token, upload_id)
    assert refused.status_code == 400 and "closed" in refused.json()["error"]
    with harness.state.factory() as session:
        assert session.scalar(select(func.count()).select_from(Submission)) == 0
    assert not list(harness.settings.submissions_dir.iterdir())
    set_challenge_open(harness.state.factory, "toy", is_open=True)
    assert harness.finalize(token, upload_id).status_code == 201  # kept until it expires
