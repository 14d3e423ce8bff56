"""Resumable uploads: ``POST /api/uploads`` -> ``PUT /api/uploads/{id}?offset=N`` -> finalize.

Bodies are streamed to disk as they arrive (``request.stream()``), never parsed into
memory. Finalizing validates the submission and queues it (see ``submissions.py``).
Invalid submissions (and uploads corrupted in transit) count toward a per-account limit,
``max_rejected_uploads`` per ``rejected_upload_window_s``: past it, opening and finalizing
uploads answer 429, so a costly bad archive cannot be sent again and again.
"""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Query, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse, Response
from pydantic import BaseModel, Field
from starlette.requests import ClientDisconnect

from semantic3d.core.errors import SubmissionError
from semantic3d.evaluation import MethodInfo
from semantic3d.server.errors import InvalidInputError
from semantic3d.server.models import Submission
from semantic3d.server.submissions import (
    check_upload_allowed,
    finalize_upload,
    submission_dict,
)
from semantic3d.server.throttle import RateLimiter, limiter_in
from semantic3d.server.uploads import (
    cancel_upload,
    create_upload,
    get_upload,
    list_uploads,
    write_chunk,
)
from semantic3d.server.web import ServerState, api_user, state_of

router = APIRouter(prefix="/api/uploads", tags=["uploads"])

MAX_RUNTIME_S = 1e7
"""Largest run time a method card may state (115 days); also refuses ``1e308``."""


def rejection_limiter(state: ServerState) -> RateLimiter:
    """The server's rejected-uploads-per-account limit."""
    settings = state.settings
    return limiter_in(
        state.extra,
        "rejected-uploads",
        limit=settings.max_rejected_uploads,
        window_s=settings.rejected_upload_window_s,
    )


def _check_rejections(state: ServerState, user_id: int) -> None:
    rejection_limiter(state).check(str(user_id), "invalid submissions from your account")


class UploadRequest(BaseModel):
    """Open an upload: what is coming and how big it is."""

    challenge: str = Field(max_length=64)
    size_bytes: int = Field(gt=0)
    filename: str = Field(default="submission.zip", max_length=1000)
    sha256: str | None = Field(default=None, description="hex digest; makes create resumable")


class MethodCard(BaseModel):
    """The method description shown on the leaderboard."""

    name: str = Field(min_length=1, max_length=200)
    description: str = Field(default="", max_length=20_000)
    paper_url: str = Field(default="", max_length=500)
    code_url: str = Field(default="", max_length=500)
    runtime_s: float | None = Field(default=None, ge=0, le=MAX_RUNTIME_S, allow_inf_nan=False)
    hardware: str | None = Field(default=None, max_length=200)

    def to_method(self) -> MethodInfo:
        return MethodInfo(
            name=self.name,
            runtime_s=self.runtime_s,
            hardware=self.hardware,
            description=self.description,
            paper_url=self.paper_url,
            code_url=self.code_url,
        )


class FinalizeRequest(BaseModel):
    """Finish an upload: the method card of the submission."""

    method: MethodCard


@router.post("", status_code=201)
def open_upload(request: Request, body: UploadRequest) -> dict[str, Any]:
    """Open (or, same challenge/size/sha256, resume) an upload session."""
    user = api_user(request)
    state = state_of(request)
    _check_rejections(state, user.id)
    check_upload_allowed(state.factory, state.settings, user_id=user.id, challenge=body.challenge)
    upload = create_upload(
        state.factory,
        state.settings,
        user_id=user.id,
        challenge=body.challenge,
        size_bytes=body.size_bytes,
        filename=body.filename,
        sha256=body.sha256,
    )
    return upload.to_dict() | {"max_chunk_bytes": state.settings.max_chunk_bytes}


@router.get("")
def open_uploads(request: Request) -> dict[str, Any]:
    """Your unfinished uploads (oldest first): resume or delete them."""
    user = api_user(request)
    state = state_of(request)
    uploads = list_uploads(state.factory, state.settings, user_id=user.id)
    return {
        "uploads": [upload.to_dict() for upload in uploads],
        "max_open_uploads": state.settings.max_open_uploads,
    }


@router.get("/{upload_id}")
def upload_status(request: Request, upload_id: str) -> dict[str, Any]:
    """How many bytes arrived: where to resume."""
    user = api_user(request)
    state = state_of(request)
    return get_upload(state.factory, state.settings, upload_id, user_id=user.id).to_dict()


@router.put("/{upload_id}")
async def put_chunk(
    request: Request, upload_id: str, offset: int = Query(ge=0, description="first byte")
) -> Response:
    """Append the request body at ``offset`` (must equal the bytes received so far)."""
    user = await run_in_threadpool(api_user, request)
    state = state_of(request)
    upload = await run_in_threadpool(
        get_upload, state.factory, state.settings, upload_id, user_id=user.id
    )
    header = request.headers.get("content-length")
    try:
        content_length = int(header) if header is not None else None
    except ValueError:
        raise InvalidInputError(f"Content-Length: expected an integer, found {header!r}") from None
    try:
        received = await write_chunk(
            state.settings,
            upload,
            offset=offset,
            content_length=content_length,
            chunks=request.stream(),
        )
    except ClientDisconnect:
        return Response(status_code=499)  # nobody is listening; the bytes that came are kept
    return JSONResponse(
        {
            "id": upload.id,
            "received_bytes": received,
            "size_bytes": upload.size_bytes,
            "complete": received >= upload.size_bytes,
        }
    )


@router.delete("/{upload_id}", status_code=204)
def abandon_upload(request: Request, upload_id: str) -> Response:
    """Abandon an upload and delete its bytes (409 while it is being written or finalized)."""
    user = api_user(request)
    state = state_of(request)
    cancel_upload(state.factory, state.settings, upload_id, user_id=user.id)
    return Response(status_code=204)


@router.post("/{upload_id}/finalize", status_code=201)
def finalize(request: Request, upload_id: str, body: FinalizeRequest) -> dict[str, Any]:
    """Validate the complete upload and queue it for evaluation.

    422 lists every problem of an invalid submission (nothing is kept); 429 when the
    quota does not allow a submission now (the upload is kept until it expires).
    """
    user = api_user(request)
    state = state_of(request)
    _check_rejections(state, user.id)
    try:
        submission = finalize_upload(
            state.factory,
            state.settings,
            state.challenges,
            user_id=user.id,
            upload_id=upload_id,
            method=body.method.to_method(),
        )
    except SubmissionError:
        rejection_limiter(state).hit(str(user.id))
        raise
    except InvalidInputError as exc:
        if "corrupted in transit" in str(exc):
            rejection_limiter(state).hit(str(user.id))
        raise
    state.leaderboards.invalidate(None)
    with state.factory() as session:
        return submission_dict(session.get_one(Submission, submission.id), owner=True)
