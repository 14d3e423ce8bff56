"""The job queue: exclusive leases, take-over after expiry, fencing, the sweeper."""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import pytest

from semantic3d.server.models import Job, Submission
from semantic3d.server.services import queue
from semantic3d.server.services.scores import StoredScores

from .conftest import (
    Harness,
    build_harness,
    ground_truth_arrays,
    make_settings,
    noisy_predictions,
    submission_zip,
)

LEASE_S = 0.3


def _scores(result: dict[str, int], *, mean_iou: float) -> StoredScores:
    """Stored fields of a stand-in result (the queue stores what it is given)."""
    return StoredScores(
        mean_iou=mean_iou,
        overall_accuracy=0.5,
        iou_json=json.dumps([mean_iou] * 8),
        result_json=json.dumps(result),
    )


@pytest.fixture
def short_leases(tmp_path: Path, ground_truth_dir: Path) -> Iterator[Harness]:
    settings = make_settings(tmp_path / "data", job_lease_s=LEASE_S, job_max_attempts=2)
    yield from build_harness(settings, ground_truth_dir)


def _queue_one(harness: Harness, user: str = "alice") -> int:
    token = harness.user_token(user)
    response = harness.submit(token, submission_zip(noisy_predictions(ground_truth_arrays(), 0.9)))
    assert response.status_code == 201
    return int(response.json()["id"])


def _job(harness: Harness, submission_id: int) -> Job:
    with harness.state.factory() as session:
        submission = session.get(Submission, submission_id)
        return submission.job


def test_a_job_is_leased_by_one_worker_only(short_leases: Harness) -> None:
    _queue_one(short_leases)
    factory, settings = short_leases.state.factory, short_leases.settings
    first = queue.lease_next(factory, settings, "w1")
    assert first is not None and first.attempt == 1
    assert queue.lease_next(factory, settings, "w2") is None


def test_an_expired_lease_is_taken_over_and_the_stale_worker_fenced_out(
    short_leases: Harness,
) -> None:
    submission_id = _queue_one(short_leases)
    factory, settings = short_leases.state.factory, short_leases.settings
    stale = queue.lease_next(factory, settings, "w1")
    assert stale is not None
    assert queue.renew(factory, settings, stale, done=5, total=10) is True
    assert _job(short_leases, submission_id).progress_done == 5
    time.sleep(LEASE_S * 1.5)
    fresh = queue.lease_next(factory, settings, "w2")
    assert fresh is not None and fresh.attempt == 2 and fresh.job_id == stale.job_id
    # The stale worker can no longer renew, finish or fail the job.
    assert queue.renew(factory, settings, stale, done=6, total=10) is False
    assert queue.fail(factory, stale, "boom") is False
    assert (
        queue.complete(
            factory,
            stale,
            scores=_scores({"x": 1}, mean_iou=0.5),
            progress_total=1,
        )
        is False
    )
    assert _job(short_leases, submission_id).status == "running"
    assert queue.complete(
        factory,
        fresh,
        scores=_scores({"x": 2}, mean_iou=0.25),
        progress_total=1,
    )
    with factory() as session:
        submission = session.get(Submission, submission_id)
        assert json.loads(submission.result_json) == {"x": 2}
        assert submission.in_flight is False and submission.job.status == "done"


def test_sweeper_fails_a_job_whose_workers_keep_dying(short_leases: Harness) -> None:
    submission_id = _queue_one(short_leases)
    factory, settings = short_leases.state.factory, short_leases.settings
    for attempt in (1, 2):
        lease = queue.lease_next(factory, settings, f"dying-{attempt}")
        assert lease is not None and lease.attempt == attempt
        time.sleep(LEASE_S * 1.5)
    assert queue.lease_next(factory, settings, "w3") is None  # attempts exhausted
    report = queue.sweep(factory, settings)
    assert report.failed_attempts == 1
    job = _job(short_leases, submission_id)
    assert job.status == "failed" and "stopped 2 times" in job.error
    with factory() as session:
        assert session.get(Submission, submission_id).in_flight is False


def test_sweeper_fails_a_job_past_the_time_limit(short_leases: Harness) -> None:
    submission_id = _queue_one(short_leases)
    factory = short_leases.state.factory
    settings = replace_settings(short_leases, job_time_limit_s=0.2)
    lease = queue.lease_next(factory, settings, "slow")
    assert lease is not None
    time.sleep(0.3)
    assert queue.renew(factory, settings, lease, done=1, total=2) is True  # still alive...
    assert queue.sweep(factory, settings).failed_time_limit == 1  # ...but too slow
    assert "time limit" in _job(short_leases, submission_id).error
    assert queue.renew(factory, settings, lease, done=2, total=2) is False


def replace_settings(harness: Harness, **changes: object):
    return harness.settings.model_copy(update=changes)


def test_a_released_job_does_not_count_as_an_attempt(short_leases: Harness) -> None:
    _queue_one(short_leases)
    factory, settings = short_leases.state.factory, short_leases.settings
    lease = queue.lease_next(factory, settings, "w1")
    assert queue.release(factory, lease) is True
    again = queue.lease_next(factory, settings, "w2")
    assert again is not None and again.attempt == 1


def test_jobs_are_served_oldest_first(harness: Harness) -> None:
    ids = [_queue_one(harness, user) for user in ("u1-a", "u2-b", "u3-c")]
    factory, settings = harness.state.factory, harness.settings
    leased = [queue.lease_next(factory, settings, "w").submission_id for _ in ids]
    assert leased == ids
    assert queue.queue_counts(factory) == {"running": 3}


def test_worker_records_progress_and_identical_results_on_retry(harness: Harness) -> None:
    submission_id = _queue_one(harness)
    assert harness.work()
    with harness.state.factory() as session:
        first = session.get(Submission, submission_id).result_json
    queue.requeue(harness.state.factory, submission_id)
    assert harness.work()
    with harness.state.factory() as session:
        submission = session.get(Submission, submission_id)
        assert submission.result_json == first
        assert submission.job.attempts == 1


def test_lease_record_is_fenced_by_attempt(short_leases: Harness) -> None:
    _queue_one(short_leases)
    factory, settings = short_leases.state.factory, short_leases.settings
    lease = queue.lease_next(factory, settings, "w1")
    forged = replace(lease, attempt=lease.attempt + 1)
    assert queue.renew(factory, settings, forged, done=1, total=1) is False


def test_requeue_refuses_a_job_in_flight_and_unknown_ids(harness: Harness) -> None:
    from semantic3d.server.errors import ConflictError, NotFoundError

    submission_id = _queue_one(harness)
    with pytest.raises(ConflictError, match="already queued"):
        queue.requeue(harness.state.factory, submission_id)
    with pytest.raises(NotFoundError, match="no submission #999"):
        queue.requeue(harness.state.factory, 999)


def test_an_evaluation_leaves_the_web_server_a_core(
    tmp_path: Path, ground_truth_dir: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from semantic3d.core import threads
    from semantic3d.server import worker

    seen: list[int] = []
    evaluate = worker.evaluate_submission

    def recording(*args: object, **kwargs: object) -> object:
        seen.append(threads.thread_budget())
        return evaluate(*args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(worker, "evaluate_submission", recording)
    monkeypatch.setattr(threads, "available_cores", lambda: 4)
    for configured, expected in ((None, 3), (1, 1)):
        settings = make_settings(tmp_path / str(configured), evaluation_threads=configured)
        assert settings.evaluation_thread_budget == expected
        for harness in build_harness(settings, ground_truth_dir):
            _queue_one(harness)
            assert harness.work()
        assert seen[-1] == expected
