"""The typed API: every JSON route names its model, the client returns those models, and
the client's handling of 503 (busy), 507 (disk full) and 408 (stalled upload)."""

from __future__ import annotations

import asyncio
import shutil
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import pytest

from semantic3d.evaluation import MethodInfo
from semantic3d.server import schemas
from semantic3d.server.client import BenchmarkClient, ClientError
from semantic3d.server.errors import ServiceUnavailableError
from semantic3d.server.routers import uploads as uploads_router
from semantic3d.server.services import upload_files

from .conftest import (
    Harness,
    build_harness,
    ground_truth_arrays,
    make_settings,
    noisy_predictions,
    submission_zip,
)

# The client gives finalize an hour; Starlette's in-process test client ignores timeouts.
pytestmark = pytest.mark.filterwarnings("ignore:You should not use the 'timeout' argument")

_JSON = "application/json"


def _client(harness: Harness, token: str, *, retries: int = 3) -> tuple[BenchmarkClient, list]:
    """A client talking to the app in-process, recording the waits instead of sleeping."""
    waits: list[float] = []
    client = BenchmarkClient(
        "http://testserver", token, client=harness.client, retries=retries, sleep=waits.append
    )
    return client, waits


def _zip(tmp_path: Path, accuracy: float = 0.9) -> Path:
    path = tmp_path / "preds.zip"
    path.write_bytes(submission_zip(noisy_predictions(ground_truth_arrays(), accuracy)))
    return path


def test_the_openapi_schema_names_a_response_model_for_every_json_route(
    harness: Harness,
) -> None:
    spec = harness.client.app.openapi()  # type: ignore[attr-defined]
    components = spec["components"]["schemas"]
    checked = []
    for path, operations in spec["paths"].items():
        for method, operation in operations.items():
            where = f"{method.upper()} {path}"
            success = {
                status: response
                for status, response in operation["responses"].items()
                if status.startswith("2")
            }
            assert success, f"{where}: no success response documented"
            for status, response in success.items():
                content = response.get("content", {})
                if status == "204" or _JSON not in content:
                    assert status == "204" or path.endswith(".csv"), f"{where}: {content}"
                    continue
                ref = content[_JSON]["schema"].get("$ref", "")
                name = ref.rpartition("/")[2]
                assert name in components, f"{where} {status}: no named model ({ref!r})"
                assert hasattr(schemas, name), f"{where}: {name} is not in server/schemas.py"
                checked.append(where)
            for status, response in operation["responses"].items():
                if status[0] in "45" and _JSON in response.get("content", {}):
                    ref = response["content"][_JSON]["schema"].get("$ref", "")
                    assert ref.endswith("/ErrorBody"), f"{where} {status}: {ref!r}"
    # Every JSON route of the API, the health check included.
    assert len(checked) == 14, checked
    assert "GET /api/challenges/{name}/leaderboard" in checked
    assert "GET /challenges/{name}/leaderboard.json" in checked  # the board's JSON download


def test_the_client_returns_typed_objects(harness: Harness, tmp_path: Path) -> None:
    token = harness.user_token("alice")
    client, waits = _client(harness, token)
    assert client.me() == schemas.Account(username="alice", is_admin=False)
    assert "toy" in {challenge.name for challenge in client.challenges()}
    queued = client.submit(
        _zip(tmp_path), challenge="toy", method=MethodInfo("Forest", runtime_s=12.5)
    )
    assert isinstance(queued, schemas.SubmissionInfo)
    assert queued.status == "queued" and queued.scores is None and queued.filename == "preds.zip"
    assert queued.method.to_method() == MethodInfo("Forest", runtime_s=12.5)
    assert client.uploads().uploads == []  # finalized: no longer open
    assert harness.work()
    done = client.wait(queued.id, poll_s=0)
    assert done.finished and done.status == "done" and done.error is None
    assert done.scores is not None and 0 < (done.scores.mean_iou or 0) <= 1
    assert done.scores.n_points == sum(int((v > 0).sum()) for v in ground_truth_arrays().values())
    assert done.scores.confusion is not None and len(done.scores.iou) == 8
    published = client.publish(queued.id)
    assert published.published
    board = client.leaderboard("toy")
    assert isinstance(board, schemas.Leaderboard)
    (entry,) = board.entries
    assert entry.rank == 1 and entry.submission_id == queued.id and entry.method == "Forest"
    assert entry.mean_iou == done.scores.mean_iou and entry.submitted_at is not None
    assert [s.id for s in client.submissions()] == [queued.id]
    assert waits == []
    # Owner-only fields are absent (not null) for everyone else.
    public = harness.client.get(f"/api/submissions/{queued.id}", headers={"Authorization": ""})
    assert public.status_code == 200
    assert not {"filename", "sha256", "error", "attempts"} & set(public.json())


def _busy_then(real: Any, n_busy: list[int], retry_after_s: int) -> Any:
    def busy(*args: Any, **kwargs: Any) -> Any:
        if n_busy[0] > 0:
            n_busy[0] -= 1
            raise ServiceUnavailableError("the server is busy", retry_after_s=retry_after_s)
        return real(*args, **kwargs)

    return busy


def test_a_busy_server_is_retried_after_the_delay_it_advertises(
    harness: Harness, monkeypatch: pytest.MonkeyPatch
) -> None:
    client, waits = _client(harness, harness.user_token("bob"), retries=3)
    busy = [2]
    monkeypatch.setattr(
        uploads_router, "list_uploads", _busy_then(uploads_router.list_uploads, busy, 7)
    )
    assert client.uploads().uploads == []
    assert waits == [7.0, 7.0] and busy == [0]


def test_a_server_that_stays_busy_ends_in_one_clear_line(
    harness: Harness, monkeypatch: pytest.MonkeyPatch
) -> None:
    client, waits = _client(harness, harness.user_token("carol"), retries=2)
    monkeypatch.setattr(
        uploads_router, "list_uploads", _busy_then(uploads_router.list_uploads, [99], 3)
    )
    with pytest.raises(ClientError) as caught:
        client.uploads()
    message = str(caught.value)
    assert caught.value.status == 503 and "\n" not in message
    assert message == (
        "503: server busy: the server is busy (still busy after 2 retries; try again later)"
    )
    assert waits == [3.0, 3.0]  # the advertised delay, a bounded number of times


def test_a_busy_chunk_is_sent_again_after_the_advertised_delay(
    harness: Harness, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    client, waits = _client(harness, harness.user_token("dora"))
    busy = [1]
    real = uploads_router.write_chunk

    async def busy_once(*args: Any, **kwargs: Any) -> int:
        if busy[0]:
            busy[0] -= 1
            raise ServiceUnavailableError("busy", retry_after_s=4)
        return await real(*args, **kwargs)

    monkeypatch.setattr(uploads_router, "write_chunk", busy_once)
    path = _zip(tmp_path)
    upload_id = client.upload(path, challenge="toy")
    assert client.upload_status(upload_id).received_bytes == path.stat().st_size
    assert waits == [4.0]


@pytest.fixture
def margin_harness(tmp_path: Path, ground_truth_dir: Path) -> Iterator[Harness]:
    settings = make_settings(tmp_path / "data", min_free_bytes=10 << 20)
    yield from build_harness(settings, ground_truth_dir)


def test_a_full_disk_507_ends_the_upload_at_once(
    margin_harness: Harness, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    harness = margin_harness
    client, waits = _client(harness, harness.user_token("erin"))
    path = _zip(tmp_path)
    size = path.stat().st_size
    free = [(10 << 20) + size // 2]
    real = shutil.disk_usage
    monkeypatch.setattr(upload_files.shutil, "disk_usage", lambda p: real(p)._replace(free=free[0]))
    with pytest.raises(ClientError) as refused:
        client.upload(path, challenge="toy")  # opening it: cannot fit
    assert refused.value.status == 507
    assert str(refused.value).startswith(
        "507: the server is out of disk space: not enough free disk space on the server"
    )
    free[0] = (10 << 20) + size
    opened = client.open_upload(challenge="toy", size_bytes=size, filename=path.name)
    free[0] = 10 << 20  # filled meanwhile: the chunk is refused, and not retried
    with pytest.raises(ClientError, match=r"^507: the server is out of disk space: ") as caught:
        client.upload(path, challenge="toy")
    assert "\n" not in str(caught.value) and waits == []
    assert client.upload_status(opened.id).received_bytes == 0


@pytest.fixture
def stall_harness(tmp_path: Path, ground_truth_dir: Path) -> Iterator[Harness]:
    settings = make_settings(tmp_path / "data", upload_read_timeout_s=0.2)
    yield from build_harness(settings, ground_truth_dir)


def _stalling(n_stalls: list[int], keep_bytes: int) -> Any:
    """``write_chunk`` whose body stops after ``keep_bytes`` bytes the first times."""
    real = upload_files.write_chunk

    async def write_chunk(settings: Any, upload: Any, **kwargs: Any) -> int:
        if n_stalls[0] <= 0:
            return await real(settings, upload, **kwargs)
        n_stalls[0] -= 1
        chunks = kwargs.pop("chunks")

        async def stalls() -> AsyncIterator[bytes]:
            async for piece in chunks:
                yield piece[:keep_bytes]
                break
            await asyncio.sleep(3600)  # the connection stays open, nothing more comes

        kwargs["content_length"] = None
        return await real(settings, upload, chunks=stalls(), **kwargs)

    return write_chunk


def test_a_stalled_chunk_408_is_resumed_from_where_the_server_stands(
    stall_harness: Harness, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    harness = stall_harness
    client, waits = _client(harness, harness.user_token("fred"))
    stalls = [2]
    monkeypatch.setattr(uploads_router, "write_chunk", _stalling(stalls, keep_bytes=100))
    path = _zip(tmp_path)
    upload_id = client.upload(path, challenge="toy")
    assert stalls == [0] and waits == [0.0, 0.0]  # resumed at once, twice
    assert client.upload_status(upload_id).received_bytes == path.stat().st_size
    assert client.finalize(upload_id, method=MethodInfo("resumed")).status == "queued"


def test_an_upload_that_keeps_stalling_ends_in_one_clear_line(
    stall_harness: Harness, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    harness = stall_harness
    client, _ = _client(harness, harness.user_token("gina"), retries=1)
    monkeypatch.setattr(uploads_router, "write_chunk", _stalling([99], keep_bytes=10))
    with pytest.raises(ClientError) as caught:
        client.upload(_zip(tmp_path), challenge="toy")
    assert caught.value.status == 408
    message = str(caught.value)
    assert message.startswith("408: the upload stalled: upload ") and "\n" not in message
    assert "no data for 0.2 s; the bytes received are kept" in message
