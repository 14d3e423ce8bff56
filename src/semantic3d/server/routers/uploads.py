"""Resumable uploads: ``POST /api/uploads`` -> ``PUT /api/uploads/{id}?offset=N`` -> finalize.

Bodies are streamed to disk as they arrive (``request.stream()``), never parsed into
memory. Finalizing validates the submission and queues it (see ``submissions.py``).
Invalid submissions (and uploads corrupted in transit) count toward a per-account limit,
``max_rejected_uploads`` per ``rejected_upload_window_s``: past it, opening and finalizing
uploads answer 429, so a costly bad archive cannot be sent again and again.
"""

from __future__ import annotations

from fastapi import APIRouter, Query, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import Response
from starlette.requests import ClientDisconnect

from semantic3d.core.errors import SubmissionError
from semantic3d.server.deps import CurrentUser, DbSession, State
from semantic3d.server.errors import InvalidInputError
from semantic3d.server.models import Submission
from semantic3d.server.schemas import (
    ChunkReceived,
    FinalizeRequest,
    OpenedUpload,
    SubmissionInfo,
    UploadInfo,
    UploadList,
    UploadRequest,
    error_responses,
)
from semantic3d.server.services.submissions import (
    check_upload_allowed,
    finalize_upload,
    submission_info,
)
from semantic3d.server.services.upload_files import write_chunk
from semantic3d.server.services.uploads import (
    cancel_upload,
    create_upload,
    get_upload,
    list_uploads,
)
from semantic3d.server.throttle import RateLimiter, limiter_in
from semantic3d.server.web import ServerState

router = APIRouter(
    prefix="/api/uploads",
    tags=["uploads"],
    responses=error_responses(400, 401, 403, 404, 409, 413, 422, 429, 503, 507),
)


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


@router.post("", status_code=201, response_model=OpenedUpload)
def open_upload(body: UploadRequest, user: CurrentUser, state: State) -> OpenedUpload:
    """Open (or, same challenge/size/sha256, resume) an upload session."""
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
    return OpenedUpload(
        **upload.to_info().model_dump(), max_chunk_bytes=state.settings.max_chunk_bytes
    )


@router.get("", response_model=UploadList)
def open_uploads(user: CurrentUser, state: State) -> UploadList:
    """Your unfinished uploads (oldest first): resume or delete them."""
    uploads = list_uploads(state.factory, state.settings, user_id=user.id)
    return UploadList(
        uploads=[upload.to_info() for upload in uploads],
        max_open_uploads=state.settings.max_open_uploads,
    )


@router.get("/{upload_id}", response_model=UploadInfo)
def upload_status(upload_id: str, user: CurrentUser, state: State) -> UploadInfo:
    """How many bytes arrived: where to resume."""
    return get_upload(state.factory, state.settings, upload_id, user_id=user.id).to_info()


@router.put("/{upload_id}", response_model=ChunkReceived, responses=error_responses(408))
async def put_chunk(
    request: Request,
    upload_id: str,
    user: CurrentUser,
    state: State,
    offset: int = Query(ge=0, description="first byte"),
) -> ChunkReceived | Response:
    """Append the request body at ``offset`` (must equal the bytes received so far).

    408 when the body stalls for the server's read timeout (the bytes received are kept),
    507 when the server's disk cannot take the chunk (nothing of it is kept).
    """
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
    return ChunkReceived(
        id=upload.id,
        received_bytes=received,
        size_bytes=upload.size_bytes,
        complete=received >= upload.size_bytes,
    )


@router.delete("/{upload_id}", status_code=204)
def abandon_upload(upload_id: str, user: CurrentUser, state: State) -> Response:
    """Abandon an upload and delete its bytes (409 while it is being written or finalized)."""
    cancel_upload(state.factory, state.settings, upload_id, user_id=user.id)
    return Response(status_code=204)


@router.post("/{upload_id}/finalize", status_code=201, response_model=SubmissionInfo)
def finalize(
    upload_id: str, body: FinalizeRequest, user: CurrentUser, state: State, db: DbSession
) -> SubmissionInfo:
    """Validate the complete upload and queue it for evaluation.

    422 lists every problem of an invalid submission (nothing is kept); 429 when the
    quota does not allow a submission now (the upload is kept until it expires).
    """
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
    return submission_info(db.get_one(Submission, submission.id), owner=True)
