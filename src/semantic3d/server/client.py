"""A client for the benchmark server's API (``semantic3d submit`` is a thin shell over it).

Uploads are chunked and resumable: the file's sha256 identifies the upload, so a client
that was interrupted (network, Ctrl-C, reboot) continues where the server stands when it
is run again, and a failed chunk is retried from the offset the server reports. Needs
only ``httpx`` (no web-server packages).
"""

from __future__ import annotations

import hashlib
import logging
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from semantic3d.core.errors import Semantic3DError, SubmissionError, require
from semantic3d.evaluation import MethodInfo

logger = logging.getLogger(__name__)

ProgressCallback = Callable[[int, int], None]
"""``progress(done_bytes, total_bytes)``."""

DEFAULT_CHUNK_BYTES = 64 << 20
_READ_BLOCK = 1 << 20


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
    otherwise one is created for ``server``.
    """

    def __init__(
        self,
        server: str,
        token: str | None,
        *,
        client: Any | None = None,
        timeout_s: float = 60.0,
        retries: int = 5,
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

    def close(self) -> None:
        """Close the connection pool."""
        self._http.close()

    def __enter__(self) -> BenchmarkClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # Requests ----------------------------------------------------------------------------
    def _request(self, method: str, url: str, **kwargs: Any) -> Any:
        try:
            response = self._http.request(method, url, **kwargs)
        except self._httpx.TransportError as exc:
            raise ClientError(f"{self.server}{url}: cannot reach the server ({exc})") from None
        return response

    def _json(self, response: Any, *, source: str | None = None) -> Any:
        if response.is_success:
            return response.json() if response.content else None
        try:
            body = response.json()
        except ValueError:
            body = {"error": response.text[:300] or response.reason_phrase}
        message = body.get("error", f"HTTP {response.status_code}")
        problems = body.get("problems")
        if response.status_code == 422 and problems:
            raise SubmissionError(problems, source=source)
        if response.status_code == 429 and "retry_after_s" in body:
            message = f"{message} (retry after {body['retry_after_s']} s)"
        raise ClientError(f"{response.status_code}: {message}", status=response.status_code)

    def get(self, url: str) -> Any:
        """GET ``url`` (a path on the server) and return its JSON."""
        return self._json(self._request("GET", url))

    def me(self) -> dict[str, Any]:
        """The account the token belongs to."""
        result: dict[str, Any] = self.get("/api/me")
        return result

    def leaderboard(self, challenge: str) -> dict[str, Any]:
        """A challenge's public leaderboard."""
        result: dict[str, Any] = self.get(f"/api/challenges/{challenge}/leaderboard")
        return result

    def submission(self, submission_id: int) -> dict[str, Any]:
        """A submission's status (and scores, once evaluated)."""
        result: dict[str, Any] = self.get(f"/api/submissions/{submission_id}")
        return result

    def publish(self, submission_id: int, *, published: bool = True) -> dict[str, Any]:
        """Publish (or withdraw) an evaluated submission."""
        response = self._request(
            "POST", f"/api/submissions/{submission_id}/publish", json={"published": published}
        )
        result: dict[str, Any] = self._json(response)
        return result

    # Uploads -----------------------------------------------------------------------------
    def upload(
        self,
        path: Path,
        *,
        challenge: str,
        chunk_bytes: int = DEFAULT_CHUNK_BYTES,
        sha256: str | None = None,
        progress: ProgressCallback | None = None,
    ) -> str:
        """Upload ``path`` (resuming an earlier upload of the same file); returns its id."""
        size = path.stat().st_size
        digest = sha256 or file_sha256(path)
        state = self._json(
            self._request(
                "POST",
                "/api/uploads",
                json={
                    "challenge": challenge,
                    "size_bytes": size,
                    "filename": path.name,
                    "sha256": digest,
                },
            )
        )
        upload_id = str(state["id"])
        chunk_bytes = min(chunk_bytes, int(state.get("max_chunk_bytes", chunk_bytes)))
        offset = int(state["received_bytes"])
        if offset:
            logger.info("resuming upload %s at byte %d of %d", upload_id, offset, size)
        if progress is not None:
            progress(offset, size)
        failures = 0
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
                failures += 1
                if failures > self.retries:
                    raise ClientError(f"upload {upload_id}: giving up after {exc}") from None
                time.sleep(min(30.0, 0.5 * 2**failures))
                offset = self._received(upload_id)
                continue
            if response.status_code == 409:
                body = response.json()
                if body.get("offset") is None:  # another writer: wait and re-read
                    failures += 1
                    if failures > self.retries:
                        self._json(response)
                    time.sleep(1.0)
                    offset = self._received(upload_id)
                else:
                    offset = int(body["offset"])
                continue
            if response.status_code >= 500:
                failures += 1
                if failures > self.retries:
                    self._json(response)
                time.sleep(min(30.0, 0.5 * 2**failures))
                offset = self._received(upload_id)
                continue
            offset = int(self._json(response)["received_bytes"])
            failures = 0
            if progress is not None:
                progress(offset, size)
        return upload_id

    def _received(self, upload_id: str) -> int:
        return int(self.get(f"/api/uploads/{upload_id}")["received_bytes"])

    def finalize(
        self, upload_id: str, *, method: MethodInfo, source: str | None = None
    ) -> dict[str, Any]:
        """Validate the complete upload on the server and queue it; the submission's JSON."""
        response = self._request(
            "POST",
            f"/api/uploads/{upload_id}/finalize",
            json={"method": method.to_dict()},
            timeout=self._httpx.Timeout(3600.0),
        )
        result: dict[str, Any] = self._json(response, source=source)
        return result

    def submit(
        self,
        path: Path,
        *,
        challenge: str,
        method: MethodInfo,
        chunk_bytes: int = DEFAULT_CHUNK_BYTES,
        progress: ProgressCallback | None = None,
    ) -> dict[str, Any]:
        """Upload and finalize ``path``: the queued submission's JSON."""
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
    ) -> dict[str, Any]:
        """Poll until the submission is done or failed; its final JSON."""
        start = time.monotonic()
        while True:
            state = self.submission(submission_id)
            if progress is not None and state["progress"]["total"]:
                progress(state["progress"]["done"], state["progress"]["total"])
            if state["status"] in ("done", "failed"):
                return state
            if timeout_s is not None and time.monotonic() - start > timeout_s:
                raise ClientError(
                    f"submission #{submission_id} still {state['status']} after {timeout_s} s"
                )
            time.sleep(poll_s)


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
