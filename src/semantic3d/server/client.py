"""A client for the benchmark server's API (``semantic3d submit`` is a thin shell over it).

Answers are parsed into the models of :mod:`semantic3d.server.schemas`, the ones the
server declares: the client returns typed objects, never raw JSON. Uploads are chunked
and resumable: the file's sha256 identifies the upload, so a client that was interrupted
(network, Ctrl-C, reboot) continues where the server stands when it is run again, and a
failed chunk is retried from the offset the server reports.

The server's temporary refusals are handled here: 503 (busy) is retried after the delay
its ``Retry-After`` advertises, at most ``retries`` times; 408 (a chunk that stalled) is
resumed from where the server stands, as a dropped connection is; 507 (the server's disk
is full) ends at once. Whatever cannot be retried ends as one :class:`ClientError` line.
Needs ``httpx`` and pydantic (no web-server packages).
"""

from __future__ import annotations

import hashlib
import logging
import time
from collections.abc import Callable, Iterator
from contextlib import suppress
from pathlib import Path
from typing import Any, TypeVar

from semantic3d.core.errors import Semantic3DError, SubmissionError, require
from semantic3d.evaluation import MethodInfo
from semantic3d.server.schemas import (
    Account,
    ApiModel,
    ChallengeInfo,
    ChallengeList,
    ChunkReceived,
    ErrorBody,
    Leaderboard,
    OpenedUpload,
    SubmissionInfo,
    SubmissionList,
    UploadInfo,
    UploadList,
)

logger = logging.getLogger(__name__)

ProgressCallback = Callable[[int, int], None]
"""``progress(done_bytes, total_bytes)``."""

DEFAULT_CHUNK_BYTES = 64 << 20
DEFAULT_RETRY_AFTER_S = 5.0
"""Wait before retrying a 503 that advertises no ``Retry-After``."""
MAX_RETRY_AFTER_S = 300.0
"""Longest advertised wait the client sleeps through; a longer one is capped to this."""
_READ_BLOCK = 1 << 20

M = TypeVar("M", bound=ApiModel)


class ClientError(Semantic3DError, RuntimeError):
    """The server refused a request or could not be reached; ``status`` is the HTTP status."""

    def __init__(self, message: str, *, status: int | None = None) -> None:
        super().__init__(message)
        self.status = status


def file_sha256(path: Path, *, progress: ProgressCallback | None = None) -> str:
    """The sha256 of ``path`` (hex), reporting bytes hashed."""
    size = path.stat().st_size
    hasher = hashlib.sha256()
    done = 0
    with path.open("rb") as handle:
        while block := handle.read(8 * _READ_BLOCK):
            hasher.update(block)
            done += len(block)
            if progress is not None:
                progress(done, size)
    return hasher.hexdigest()


class BenchmarkClient:
    """Talks to one server with one API token.

    ``client`` lets callers pass a ready ``httpx.Client`` (e.g. FastAPI's ``TestClient``);
    otherwise one is created for ``server``. ``retries`` bounds the retries of a request
    the server refused for now (503) and of a chunk that failed; ``sleep`` waits between
    them (``time.sleep``; tests pass a recorder).
    """

    def __init__(
        self,
        server: str,
        token: str | None,
        *,
        client: Any | None = None,
        timeout_s: float = 60.0,
        retries: int = 5,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        httpx: Any = require("httpx", "server")
        self.server = server.rstrip("/")
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        if client is None:
            client = httpx.Client(
                base_url=self.server,
                timeout=httpx.Timeout(timeout_s, write=None),
                follow_redirects=False,
            )
        client.headers.update(headers)
        self._http = client
        self._httpx = httpx
        self.retries = retries
        self._sleep = sleep

    def close(self) -> None:
        """Close the connection pool."""
        self._http.close()

    def __enter__(self) -> BenchmarkClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # Requests ----------------------------------------------------------------------------
    def _request(self, method: str, url: str, **kwargs: Any) -> Any:
        """Send a request; a 503 is retried after its ``Retry-After``, ``retries`` times."""
        busy = 0
        while True:
            try:
                response = self._http.request(method, url, **kwargs)
            except self._httpx.TransportError as exc:
                raise ClientError(f"{self.server}{url}: cannot reach the server ({exc})") from None
            if response.status_code != 503 or busy >= self.retries:
                return response
            busy += 1
            delay = retry_after_s(response)
            logger.info(
                "%s %s: server busy (503), retry %d of %d in %g s",
                method,
                url,
                busy,
                self.retries,
                delay,
            )
            self._sleep(delay)

    def _parse(self, response: Any, model: type[M], *, source: str | None = None) -> M:
        """The body of a successful ``response`` as ``model``; else the error it carries."""
        if response.is_success:
            return model.model_validate_json(response.content)
        raise self._error(response, source=source)

    def _error(self, response: Any, *, source: str | None = None) -> Exception:
        """The exception for a refused request: one line saying what to do."""
        status = response.status_code
        try:
            body = ErrorBody.model_validate_json(response.content)
        except ValueError:
            text = " ".join(response.text.split())[:300]
            body = ErrorBody(error=text or response.reason_phrase or f"HTTP {status}")
        if status == 422 and body.problems:
            return SubmissionError(body.problems, source=source)
        message = " ".join(body.error.split())
        if status == 429 and body.retry_after_s is not None:
            message = f"{message} (retry after {body.retry_after_s} s)"
        elif status == 503:
            message = (
                f"server busy: {message} (still busy after {self.retries} "
                f"{'retry' if self.retries == 1 else 'retries'}; try again later)"
            )
        elif status == 507:
            message = f"the server is out of disk space: {message}"
        elif status == 408:
            message = f"the upload stalled: {message}"
        return ClientError(f"{status}: {message}", status=status)

    def get(self, url: str, model: type[M]) -> M:
        """GET ``url`` (a path on the server), parsed as ``model``."""
        return self._parse(self._request("GET", url), model)

    def me(self) -> Account:
        """The account the token belongs to."""
        return self.get("/api/me", Account)

    def challenges(self) -> list[ChallengeInfo]:
        """Every challenge of the server."""
        return self.get("/api/challenges", ChallengeList).challenges

    def leaderboard(self, challenge: str) -> Leaderboard:
        """A challenge's public leaderboard."""
        return self.get(f"/api/challenges/{challenge}/leaderboard", Leaderboard)

    def submission(self, submission_id: int) -> SubmissionInfo:
        """A submission's status (and scores, once evaluated)."""
        return self.get(f"/api/submissions/{submission_id}", SubmissionInfo)

    def submissions(self) -> list[SubmissionInfo]:
        """The account's submissions, newest first."""
        return self.get("/api/submissions", SubmissionList).submissions

    def publish(self, submission_id: int, *, published: bool = True) -> SubmissionInfo:
        """Publish (or withdraw) an evaluated submission."""
        response = self._request(
            "POST", f"/api/submissions/{submission_id}/publish", json={"published": published}
        )
        return self._parse(response, SubmissionInfo)

    # Uploads -----------------------------------------------------------------------------
    def open_upload(
        self, *, challenge: str, size_bytes: int, filename: str, sha256: str | None = None
    ) -> OpenedUpload:
        """Open an upload, or resume the open one of the same file (same sha256)."""
        response = self._request(
            "POST",
            "/api/uploads",
            json={
                "challenge": challenge,
                "size_bytes": size_bytes,
                "filename": filename,
                "sha256": sha256,
            },
        )
        return self._parse(response, OpenedUpload)

    def upload_status(self, upload_id: str) -> UploadInfo:
        """Where an upload stands (bytes received)."""
        return self.get(f"/api/uploads/{upload_id}", UploadInfo)

    def uploads(self) -> UploadList:
        """The account's unfinished uploads."""
        return self.get("/api/uploads", UploadList)

    def upload(
        self,
        path: Path,
        *,
        challenge: str,
        chunk_bytes: int = DEFAULT_CHUNK_BYTES,
        sha256: str | None = None,
        progress: ProgressCallback | None = None,
    ) -> str:
        """Upload ``path`` (resuming an earlier upload of the same file); returns its id.

        A chunk that fails (connection lost, 408 stalled, 503 busy, other 5xx) is sent
        again from where the server stands, at most ``retries`` times in a row; 507 (no
        disk space on the server) and other refusals end the upload with one error line.
        """
        size = path.stat().st_size
        digest = sha256 or file_sha256(path)
        state = self.open_upload(
            challenge=challenge, size_bytes=size, filename=path.name, sha256=digest
        )
        upload_id = state.id
        chunk_bytes = min(chunk_bytes, state.max_chunk_bytes)
        offset = state.received_bytes
        if offset:
            logger.info("resuming upload %s at byte %d of %d", upload_id, offset, size)
        if progress is not None:
            progress(offset, size)
        failures = 0

        def failed(reason: str, delay: float, response: Any | None = None) -> None:
            nonlocal failures
            failures += 1
            if failures > self.retries:
                if response is not None:
                    raise self._error(response)
                raise ClientError(
                    f"upload {upload_id}: giving up after {self.retries} retries ({reason})"
                )
            logger.info("upload %s: %s; retry %d in %g s", upload_id, reason, failures, delay)
            self._sleep(delay)

        while offset < size:
            length = min(chunk_bytes, size - offset)
            try:
                response = self._http.put(
                    f"/api/uploads/{upload_id}",
                    params={"offset": offset},
                    content=_read_range(path, offset, length, size, progress),
                    headers={
                        "Content-Length": str(length),
                        "Content-Type": "application/octet-stream",
                    },
                )
            except self._httpx.TransportError as exc:
                failed(str(exc) or type(exc).__name__, _backoff_s(failures))
                offset = self._received(upload_id)
                continue
            status = response.status_code
            if status == 409:
                conflict = _error_body(response)
                if conflict.offset is None:  # another writer: wait and re-read
                    failed("another request is writing it", 1.0, response)
                    offset = self._received(upload_id)
                else:
                    offset = conflict.offset
                continue
            if status == 507:
                raise self._error(response)
            if status in (408, 503) or status >= 500:
                delay = retry_after_s(response) if status == 503 else _backoff_s(failures)
                if status == 408:
                    delay = 0.0  # the server kept what arrived: resume at once
                failed(f"HTTP {status}", delay, response)
                offset = self._received(upload_id)
                continue
            offset = self._parse(response, ChunkReceived).received_bytes
            failures = 0
            if progress is not None:
                progress(offset, size)
        return upload_id

    def _received(self, upload_id: str) -> int:
        return self.upload_status(upload_id).received_bytes

    def finalize(
        self, upload_id: str, *, method: MethodInfo, source: str | None = None
    ) -> SubmissionInfo:
        """Validate the complete upload on the server and queue it: the new submission."""
        response = self._request(
            "POST",
            f"/api/uploads/{upload_id}/finalize",
            json={"method": method.to_dict()},
            timeout=self._httpx.Timeout(3600.0),
        )
        return self._parse(response, SubmissionInfo, source=source)

    def submit(
        self,
        path: Path,
        *,
        challenge: str,
        method: MethodInfo,
        chunk_bytes: int = DEFAULT_CHUNK_BYTES,
        progress: ProgressCallback | None = None,
    ) -> SubmissionInfo:
        """Upload and finalize ``path``: the queued submission."""
        upload_id = self.upload(
            path, challenge=challenge, chunk_bytes=chunk_bytes, progress=progress
        )
        return self.finalize(upload_id, method=method, source=path.name)

    def wait(
        self,
        submission_id: int,
        *,
        poll_s: float = 3.0,
        timeout_s: float | None = None,
        progress: ProgressCallback | None = None,
    ) -> SubmissionInfo:
        """Poll until the submission is done or failed; its final state."""
        start = time.monotonic()
        while True:
            state = self.submission(submission_id)
            if progress is not None and state.progress.total:
                progress(state.progress.done, state.progress.total)
            if state.finished:
                return state
            if timeout_s is not None and time.monotonic() - start > timeout_s:
                raise ClientError(
                    f"submission #{submission_id} still {state.status} after {timeout_s} s"
                )
            time.sleep(poll_s)


def retry_after_s(response: Any) -> float:
    """The wait a refusal advertises (``Retry-After`` seconds, else ``retry_after_s``).

    Falls back to :data:`DEFAULT_RETRY_AFTER_S`; capped at :data:`MAX_RETRY_AFTER_S`.
    """
    header = response.headers.get("retry-after")
    delay: float | None = None
    if header is not None:
        try:
            delay = float(header)
        except ValueError:
            delay = None
    if delay is None:
        with suppress(ValueError):
            delay = _error_body(response).retry_after_s
    if delay is None or delay != delay or delay < 0:
        delay = DEFAULT_RETRY_AFTER_S
    return min(delay, MAX_RETRY_AFTER_S)


def _error_body(response: Any) -> ErrorBody:
    try:
        return ErrorBody.model_validate_json(response.content)
    except ValueError:
        return ErrorBody(error=response.text[:300])


def _backoff_s(failures: int) -> float:
    return min(30.0, 0.5 * 2 ** (failures + 1))


def _read_range(
    path: Path, offset: int, length: int, size: int, progress: ProgressCallback | None
) -> Iterator[bytes]:
    """Stream ``length`` bytes of ``path`` from ``offset`` (progress as they are handed on)."""
    with path.open("rb") as handle:
        handle.seek(offset)
        left = length
        sent = offset
        while left > 0:
            block = handle.read(min(_READ_BLOCK, left))
            if not block:
                raise ClientError(f"{path}: shorter than expected; did it change during upload?")
            left -= len(block)
            sent += len(block)
            yield block
            if progress is not None:
                progress(sent, size)
